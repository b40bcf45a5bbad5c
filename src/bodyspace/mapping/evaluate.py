"""Evaluation of the semantic mapping (Rupprecht et al. Sec. 4.2, Tables 1-2, Figures 4 and 6).

Three methods side by side on held-out *feasible* requests (the measurements of bodies sampled
like the training set, so some body meets each exactly): the linear mapping of the related work
(Table 2), the linear-leaf forest (Table 1), and the forest followed by ``refine.refine``. For
each, the body of the predicted coefficients is measured again and ``measured - requested`` (cm)
is summarized per parameter by its mean and variance, as in the paper's tables; plus the share
of requests with all six within 1 mm. Figure 6: shoulder size swept from 100 to 140 cm, the
other five held at the training set's median.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bodyspace.atomic import atomic_path
from bodyspace.mapping.forest import LinearLeafForest
from bodyspace.mapping.gradients import RUPPRECHT_SIX, LinearBodyMeasures
from bodyspace.mapping.linear import LinearMapping
from bodyspace.mapping.refine import refine
from bodyspace.mapping.training import make_training_set

METHODS = ("linear", "forest", "forest + refinement")
SWEEP_CM = (100.0, 110.0, 120.0, 130.0, 140.0)


@dataclass
class MappingEvaluation:
    """names (M,); requests (N, M) cm; errors: method → (N, M) measured − requested (cm);
    timings (s); sweep: the shoulder-size sweep (see ``shoulder_sweep``); refine_misses: count of
    held-out requests refinement reported as missed."""

    names: tuple
    requests: np.ndarray
    errors: dict
    timings: dict
    sweep: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict)

    def table(self, method: str) -> dict:
        """name → {"mean": cm, "variance": cm², "sd": cm} for one method."""
        e = self.errors[method]
        return {n: {"mean": float(e[:, j].mean()), "variance": float(e[:, j].var()), "sd": float(e[:, j].std())}
                for j, n in enumerate(self.names)}

    def within(self, method: str, tol_cm: float = 0.1) -> float:
        """Share of requests whose measurements are all within ``tol_cm`` of the request."""
        return float(np.mean(np.abs(self.errors[method]).max(axis=1) <= tol_cm))

    def to_json(self) -> dict:
        return {"units": {"mean": "cm", "variance": "cm^2"}, "names": list(self.names),
                "held_out": int(len(self.requests)), "settings": self.settings,
                "tables": {m: self.table(m) for m in self.errors},
                "within_1mm": {m: self.within(m) for m in self.errors},
                "timings_s": {k: round(v, 4) for k, v in self.timings.items()},
                "shoulder_sweep": _jsonable(self.sweep)}

    def markdown(self) -> str:
        """The layout of Tables 1 and 2, the three methods side by side (cm, cm²)."""
        head = "| parameter | " + " | ".join(f"{m} mean | {m} variance" for m in self.errors) + " |"
        rule = "|---|" + "---|---|" * len(self.errors)
        rows = [head, rule]
        tabs = {m: self.table(m) for m in self.errors}
        for n in self.names:
            rows.append(f"| {n} | " + " | ".join(f"{tabs[m][n]['mean']:.4f} | {tabs[m][n]['variance']:.4f}"
                                                 for m in self.errors) + " |")
        cells = sum(([f"{100 * self.within(m):.1f} %", ""] for m in self.errors), [])
        rows.append("| all six within 1 mm | " + " | ".join(cells) + " |")
        return (f"Error (measured − requested) in cm over {len(self.requests)} held-out feasible requests "
                "(mean in cm, variance in cm²)\n\n" + "\n".join(rows) + "\n")


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x


def _pad(z: np.ndarray, K: int) -> np.ndarray:
    out = np.zeros((len(z), K))
    out[:, :z.shape[1]] = z
    return out


def evaluate_mapping(model, samples: int = 10000, held_out: int = 1000, seed: int = 0, k: int = 25,
                     n_trees: int = 50, n_jobs: int | None = None, sweep: bool = True,
                     progress=None) -> tuple[MappingEvaluation, dict]:
    """Train the three methods on ``samples`` bodies and evaluate them on ``held_out`` requests.

    Training uses ``rng=seed``, the held-out set ``rng=seed + 1`` (both deterministic).
    Returns the evaluation and the fitted ``{"linear": ..., "forest": ...}``.
    """
    report = progress or (lambda msg, frac: None)
    timings = {}
    t = time.perf_counter()
    report("training set", 0.0)
    train = make_training_set(model, samples, k, rng=seed)
    held = make_training_set(model, held_out, k, rng=seed + 1)
    timings["training_set_s"] = time.perf_counter() - t
    kk = train.k
    X, Y = train.measurements, train.coefficients[:, :kk]
    report("linear mapping", 0.2)
    t = time.perf_counter()
    lin = LinearMapping().fit(X, Y)
    timings["linear_fit_s"] = time.perf_counter() - t
    report("forest", 0.25)
    t = time.perf_counter()
    forest = LinearLeafForest(n_trees=n_trees, random_state=seed, n_jobs=n_jobs).fit(X, Y)
    timings["forest_fit_s"] = time.perf_counter() - t
    measurer = LinearBodyMeasures.from_model(model, names=RUPPRECHT_SIX, k=kk)
    req = held.measurements
    K = model.n_components
    preds = {"linear": _pad(lin.predict(req), K)}
    t = time.perf_counter()
    preds["forest"] = _pad(forest.predict(req), K)
    timings["forest_predict_s"] = time.perf_counter() - t
    report("refinement", 0.6)
    t = time.perf_counter()
    ref = refine(model, preds["forest"], req, measurer=measurer, k=kk)
    timings["refine_s"] = time.perf_counter() - t
    timings["refine_ms_per_request"] = 1000 * timings["refine_s"] / len(req)
    preds["forest + refinement"] = ref.coefficients
    errors = {m: measurer(preds[m][:, :kk]) * 100.0 - req for m in METHODS}
    sw = shoulder_sweep(model, forest, train, measurer) if sweep else {}
    report("done", 1.0)
    ev = MappingEvaluation(train.names, req, errors, timings, sw,
                           {"samples": samples, "held_out": held_out, "seed": seed, "k": kk, "n_trees": n_trees,
                            "encoding": model.encoding, "refine_misses": int(sum(bool(m) for m in ref.misses))})
    return ev, {"linear": lin, "forest": forest}


def shoulder_sweep(model, forest, train, measurer, sizes=SWEEP_CM, name: str = "shoulder_size") -> dict:
    """Figure 6: ``name`` set to each of ``sizes`` (cm), the other parameters at the training median.

    Returns requests (S, M), coefficients (S, K) (forest + refinement), measured (S, M) cm,
    forest_measured (S, M) cm (forest alone), misses (per size: what refinement could not meet).
    """
    names = train.names
    j = names.index(name)
    base = np.median(train.measurements, axis=0)
    req = np.tile(base, (len(sizes), 1))
    req[:, j] = sizes
    K = model.n_components
    z0 = _pad(forest.predict(req), K)
    res = refine(model, z0, req, measurer=measurer, k=train.k)
    return {"names": list(names), "swept": name, "sizes_cm": list(sizes), "requests": req,
            "coefficients": res.coefficients, "measured": res.measured,
            "forest_measured": measurer(z0[:, :train.k]) * 100.0, "misses": res.misses}


def plot_errors(ev: MappingEvaluation, path) -> Path:
    """Figure-4-like PNG: per parameter, mean error (bars) and standard deviation (whiskers), and
    the variance on a log scale, for the three methods."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 4.2), dpi=110)
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    x = np.arange(len(ev.names))
    wdt = 0.8 / len(ev.errors)
    colors = ("#8c8c8c", "#2a7ab9", "#d95f02")
    for i, (m, e) in enumerate(ev.errors.items()):
        ax1.bar(x + (i - 1) * wdt, e.mean(0), wdt, yerr=e.std(0), capsize=2, label=m, color=colors[i % 3])
        ax2.bar(x + (i - 1) * wdt, np.maximum(e.var(0), 1e-12), wdt, label=m, color=colors[i % 3])
    for ax, title in ((ax1, "mean ± sd of measured − requested (cm)"), (ax2, "variance (cm², log scale)")):
        ax.set_xticks(x)
        ax.set_xticklabels([n.replace("_", " ") for n in ev.names], rotation=25, fontsize=8)
        ax.set_title(title, fontsize=10)
        ax.axhline(0, color="k", lw=0.5)
    ax2.set_yscale("log")
    ax1.legend(fontsize=8)
    fig.suptitle(f"semantic mapping on {len(ev.requests)} held-out requests", fontsize=11)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return Path(path)


def write_report(model, ev: MappingEvaluation, out) -> dict[str, Path]:
    """Write tables (Markdown + JSON), the Figure-4 PNG and the Figure-6 line-up into folder ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = {"tables": out / "mapping_tables.md", "json": out / "mapping_evaluation.json",
             "errors_png": out / "mapping_errors.png"}
    md = ev.markdown()
    if ev.sweep:
        sw = ev.sweep
        md += f"\n{sw['swept']} sweep (other parameters held at the training median; cm)\n\n"
        md += "| requested | " + " | ".join(sw["names"]) + " | missed |\n|---|" + "---|" * (len(sw["names"]) + 1) + "\n"
        for i, s in enumerate(sw["sizes_cm"]):
            miss = ", ".join(f"{k} {v['difference']:+.2f}" for k, v in sw["misses"][i].items()) or "—"
            md += f"| {s:.0f} | " + " | ".join(f"{v:.2f}" for v in sw["measured"][i]) + f" | {miss} |\n"
    with atomic_path(files["tables"]) as tmp:
        Path(tmp).write_text(md)
    with atomic_path(files["json"]) as tmp:
        Path(tmp).write_text(json.dumps(ev.to_json(), indent=2))
    plot_errors(ev, files["errors_png"])
    if ev.sweep:
        from bodyspace.report.render import contact_sheet
        sw = ev.sweep
        files["sweep_png"] = out / "shoulder_sweep.png"
        j = sw["names"].index(sw["swept"])
        bodies = model.reconstruct(np.asarray(sw["coefficients"]))
        labels = [f"{s:.0f} cm → {m[j]:.1f}" + (" (missed)" if miss else "")
                  for s, m, miss in zip(sw["sizes_cm"], sw["measured"], sw["misses"])]
        contact_sheet(bodies, model.faces, files["sweep_png"], labels=labels, views=("front", "side"),
                      title=f"{sw['swept']} from {sw['sizes_cm'][0]:.0f} to {sw['sizes_cm'][-1]:.0f} cm (Rupprecht Fig. 6)")
    return files
