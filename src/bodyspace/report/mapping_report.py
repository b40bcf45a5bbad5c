"""Tables and pictures of a mapping evaluation (``studies.mapping.evaluate_mapping``).

``mapping_tables_markdown`` lays the three methods out as Rupprecht Tables 1 and 2,
``plot_errors`` draws bars like Rupprecht Figure 4, and ``write_mapping_report`` writes both, the JSON
and the line-up of the shoulder sweep (Rupprecht Figure 6) into one folder.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from bodyspace.atomic import PNG_METADATA, atomic_path
from bodyspace.report.render import contact_sheet
from bodyspace.studies.mapping import MappingEvaluation, exact_by_construction_note

__all__ = ["format_error", "mapping_tables_markdown", "parameter_label", "plot_errors", "write_mapping_report"]


def format_error(x: float, signed: bool = True) -> str:
    """A table cell: 4 decimals, but a non-zero value too small for them in 1 significant digit
    (``6e-06``), so no error that is not 0 is printed as ``0.0000``."""
    x = float(x)
    if x != 0.0 and np.isfinite(x) and abs(x) < 5e-5:
        return f"{x:+.0e}" if signed else f"{x:.0e}"
    return f"{x:+.4f}" if signed else f"{x:.4f}"


def parameter_label(ev: MappingEvaluation, name: str) -> str:
    """The parameter's name, with `` *`` when it is exact by construction (``exact_by_construction_note``)."""
    return f"{name} *" if name in (ev.settings.get("exact_by_construction") or []) else name


def mapping_tables_markdown(ev: MappingEvaluation) -> str:
    """The layout of Rupprecht Tables 1 and 2, the three methods side by side (cm, cm²)."""
    head = "| parameter | " + " | ".join(f"{m} mean | {m} variance" for m in ev.errors) + " |"
    rule = "|---|" + "---|---|" * len(ev.errors)
    rows = [head, rule]
    tabs = {m: ev.table(m) for m in ev.errors}
    for n in ev.names:
        rows.append(f"| {parameter_label(ev, n)} | " + " | ".join(
            f"{format_error(tabs[m][n]['mean'], False)} | {format_error(tabs[m][n]['variance'], False)}"
            for m in ev.errors) + " |")
    cells = sum(([f"{100 * ev.within(m):.1f} %", ""] for m in ev.errors), [])
    rows.append(f"| all {len(ev.names)} within 1 mm | " + " | ".join(cells) + " |")
    inputs = ev.settings.get("inputs")
    said = (f"Inputs: {', '.join(inputs)} (the model's measurement set, {ev.settings.get('measurement_set')})\n\n"
            if inputs else "")
    note = exact_by_construction_note(ev)
    return (f"{said}Error (measured − requested) in cm over {len(ev.requests)} held-out feasible requests "
            "(mean in cm, variance in cm²)\n\n" + "\n".join(rows) + "\n" + (f"\n{note}\n" if note else ""))


def plot_errors(ev: MappingEvaluation, path) -> Path:
    """PNG like Rupprecht Figure 4: per parameter, mean error (bars) and standard deviation (whiskers), and
    the variance on a log scale, for the three methods."""
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
        fig.savefig(tmp, format="png", metadata=PNG_METADATA)
    return Path(path)


def write_mapping_report(model, ev: MappingEvaluation, out) -> dict[str, Path]:
    """Write tables (Markdown + JSON), the PNG of Rupprecht Figure 4 and the line-up of Rupprecht Figure 6 into folder ``out``.

    ``model`` (the evaluated BodyModel) decodes the sweep's bodies for the line-up. Returns
    {"tables", "json", "errors_png"[, "sweep_png"]: path}.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = {"tables": out / "mapping_tables.md", "json": out / "mapping_evaluation.json",
             "errors_png": out / "mapping_errors.png"}
    md = mapping_tables_markdown(ev)
    if ev.sweep:
        sw = ev.sweep
        md += f"\n{sw['swept']} sweep (other parameters held at the training median; cm)\n\n"
        md += "| requested | " + " | ".join(sw["names"]) + " | missed |\n|---|" + "---|" * (len(sw["names"]) + 1) + "\n"
        for i, s in enumerate(sw["sizes_cm"]):
            miss = ", ".join(f"{k} {v['difference']:+.2f}" for k, v in sw["misses"][i].items()) or "—"
            md += f"| {s:g} | " + " | ".join(f"{v:.2f}" for v in sw["measured"][i]) + f" | {miss} |\n"
    with atomic_path(files["tables"]) as tmp:
        Path(tmp).write_text(md)
    with atomic_path(files["json"]) as tmp:
        Path(tmp).write_text(json.dumps(ev.to_json(), indent=2))
    plot_errors(ev, files["errors_png"])
    if ev.sweep:
        sw = ev.sweep
        files["sweep_png"] = out / "shoulder_sweep.png"
        j = sw["names"].index(sw["swept"])
        bodies = model.reconstruct(np.asarray(sw["coefficients"]))
        labels = [f"{s:g} cm → {m[j]:.1f}" + (" (missed)" if miss else "")
                  for s, m, miss in zip(sw["sizes_cm"], sw["measured"], sw["misses"])]
        contact_sheet(bodies, model.faces, files["sweep_png"], labels=labels, views=("front", "side"),
                      title=f"{sw['swept']} from {sw['sizes_cm'][0]:g} to {sw['sizes_cm'][-1]:g} cm (Rupprecht Figure 6)")
    return files
