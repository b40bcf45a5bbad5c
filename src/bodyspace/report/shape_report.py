"""Tables (Markdown + JSON) and PNGs of the two shape-space studies.

``write_interpolation_report`` writes ``studies.interpolation.interpolation_study``'s result
(Hasler Figure 5: pose A, the halfway mesh per encoder, pose B); ``write_generalization_report``
writes ``studies.generalization.generalization_study``'s (error against the number of components).
The studies themselves, their definitions and their costs are in ``bodyspace.studies``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from bodyspace.atomic import PNG_METADATA, atomic_path, write_json
from bodyspace.mesh.alignment import rigid_procrustes
from bodyspace.report.render import contact_sheet

__all__ = ["generalization_in_mm", "write_generalization_report", "write_interpolation_report"]


def write_interpolation_report(result: dict, faces: np.ndarray, out, stem: str = "interpolation") -> dict:
    """Write ``{stem}.md``, ``{stem}.json`` and ``{stem}.png`` (pose A, halfway per encoder,
    pose B) into folder ``out``; returns their file names."""
    out = Path(out)
    names = list(result["summary"])
    lines = [f"# Halfway between two scans of one subject ({result['pairs']} pairs, subjects "
             f"{', '.join(result['subjects'])})", "",
             "Mean relative edge-length change and relative volume change of the halfway mesh against the "
             "endpoints' average (percent).", "",
             "| subject | pose A | pose B | " + " | ".join(f"{n} edge % | {n} volume %" for n in names) + " |",
             "|---|---|---|" + "---|---|" * len(names)]
    for r in result["rows"]:
        lines.append(f"| {r['subject']} | {r['pose_a']} | {r['pose_b']} | " + " | ".join(
            f"{100 * r[f'{n}_edge_change']:.2f} | {100 * r[f'{n}_volume_change']:+.2f}" for n in names) + " |")
    lines += ["", "| encoding | edge % mean | edge % max | abs volume % mean | abs volume % max |", "|---|---|---|---|---|"]
    for n, s in result["summary"].items():
        lines.append(f"| {n} | {100 * s['edge_change_mean']:.2f} | {100 * s['edge_change_max']:.2f} | "
                     f"{100 * s['volume_change_abs_mean']:.2f} | {100 * s['volume_change_abs_max']:.2f} |")
    with atomic_path(out / f"{stem}.md") as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    payload = {k: v for k, v in result.items() if k != "example"}
    payload["example"] = {k: result["example"][k] for k in ("pair", "scan_a", "scan_b")}
    payload["units"] = {"edge_change": "fraction (mean over edges of |l - l_ref| / l_ref)",
                        "volume_change": "fraction ((V - V_ref) / V_ref)"}
    write_json(out / f"{stem}.json", payload)
    ex = result["example"]
    row = result["rows"][ex["pair"]]
    meshes = [ex["a"]] + [ex["halfway"][n] for n in names] + [ex["b"]]
    labels = [f"A: {row['pose_a']}"] + [
        f"{n} halfway\nedge {100 * row[f'{n}_edge_change']:.1f}%, vol {100 * row[f'{n}_volume_change']:+.1f}%"
        for n in names] + [f"B: {row['pose_b']}"]
    # Stand the endpoints in the same frame as the decoded meshes (placed on the mean model).
    ref = meshes[1]
    meshes = [rigid_procrustes(m, ref)[0] if i in (0, len(meshes) - 1) else m for i, m in enumerate(meshes)]
    contact_sheet(np.stack(meshes), faces, out / f"{stem}.png", labels=labels, views=("front", "side"),
                  title=f"subject {row['subject']}: halfway in code space")
    return {"table": f"{stem}.md", "json": f"{stem}.json", "png": f"{stem}.png"}


def generalization_in_mm(result: dict) -> dict:
    """``generalization_study``'s result with its errors in mm: ``error_mm``, ``local_error_mm``,
    ``max_error_mm``, ``error_mm_per_fold`` in place of the ``*_m`` fields (metres); everything
    else as it is."""
    keys = {"error_m": "error_mm", "local_error_m": "local_error_mm", "max_error_m": "max_error_mm",
            "error_m_per_fold": "error_mm_per_fold"}
    out = {}
    for k, v in result.items():
        if k in keys:
            out[keys[k]] = {name: (1000.0 * np.asarray(e, dtype=float)).tolist() for name, e in v.items()}
        else:
            out[k] = v
    return out


# Column titles of the models a study measures: "<encoder> <projection>" or "<encoder>".
_PROJECTION_TITLES = {"code": "code projection", "vertex": "vertex fit"}
_SELECTION_TITLES = {"rest": "shape-only model (rest scans)", "all": "pose+shape model (all scans)"}


def _model_title(key: str, result: dict) -> str:
    """"vertex PCA", "rre PCA, vertex fit", ... for a result key (``studies.generalization.model_names``)."""
    info = result.get("models", {}).get(key)
    if info is None:
        return key
    if key == info["encoder"]:
        return f"{key} PCA"
    order = {"vertex": " (vertex-ordered)", "refined": " (vertex-ordered, refined)"}.get(info.get("basis", "code"), "")
    return f"{info['encoder']} PCA{order}, {_PROJECTION_TITLES.get(info['projection'], info['projection'])}"


def _generalization_section(result: dict) -> list[str]:
    names = list(result["error_mm"])
    titles = [_model_title(n, result) for n in names]
    local = result.get("local_error_mm", {})
    worst = result.get("max_error_mm", {})
    fit_s = result.get("fit_s", {})
    sel = result["selection"]
    lines = [f"## {_SELECTION_TITLES.get(sel, sel)}: {len(result['folds'])} held-out subjects, "
             f"{result.get('held_out_scans', '?')} held-out scans, {result.get('training_subjects', '?')} training "
             "subjects", "",
             "Mean vertex distance (mm) between a held-out scan and its reconstruction from the first k components, "
             "the scan aligned rigidly onto the reconstruction.", "",
             "| k | " + " | ".join(titles) + " |", "|---|" + "---|" * len(names)]
    for j, k in enumerate(result["components"]):
        best = min(result["error_mm"][n][j] for n in names)
        cells = [f"{result['error_mm'][n][j]:.1f}" for n in names]
        cells = [f"**{c}**" if result["error_mm"][n][j] == best else c for c, n in zip(cells, names)]
        lines.append(f"| {k} | " + " | ".join(cells) + " |")
    if worst:
        lines += ["", "Largest vertex distance (mm) over all held-out scans:", "",
                  "| k | " + " | ".join(titles) + " |", "|---|" + "---|" * len(names)]
        for j, k in enumerate(result["components"]):
            lines.append(f"| {k} | " + " | ".join(f"{worst[n][j]:.0f}" for n in names) + " |")
    if local:
        lines += ["", f"\"Local\": the same after aligning each of {result.get('local_regions', '?')} body regions "
                  "rigidly (turned or shifted limbs removed, docs/encoding.md, \"Generalization\"):", "",
                  "| k | " + " | ".join(titles) + " |", "|---|" + "---|" * len(names)]
        for j, k in enumerate(result["components"]):
            lines.append(f"| {k} | " + " | ".join(f"{local[n][j]:.1f}" for n in names) + " |")
    if fit_s:
        lines += ["", "Seconds per mesh (projection and decode, this run's machine):", "",
                  "| k | " + " | ".join(titles) + " |", "|---|" + "---|" * len(names)]
        for j, k in enumerate(result["components"]):
            lines.append(f"| {k} | " + " | ".join(f"{fit_s[n][j]:.2f}" for n in names) + " |")
    return lines


def write_generalization_report(results, out, stem: str = "generalization") -> dict:
    """Write ``{stem}.md``, ``{stem}.json`` (errors in mm) and a ``{stem}.png`` plot into ``out``
    for one ``generalization_study`` result or a list of them (e.g. the shape-only and the
    pose+shape study): a table and a panel each."""
    out = Path(out)
    results = [results] if isinstance(results, dict) else list(results)
    results = [generalization_in_mm(r) for r in results]
    lines = ["# Leave-one-subject-out reconstruction error", "",
             "RRE is measured with both ways of projecting a mesh on its shape space (`ShapeSpace.project`): the "
             "code projection (encode, project the code) and the vertex fit (fit the coefficients to the mesh "
             "through the decoder, docs/encoding.md); for vertex PCA the two are one. Best per row in bold.", ""]
    for r in results:
        lines += _generalization_section(r) + [""]
    with atomic_path(out / f"{stem}.md") as tmp:
        tmp.write_text("\n".join(lines))
    payload = {"studies": [{**r, "units": {"error": "mm", "fit_s": "s"}} for r in results]}
    write_json(out / f"{stem}.json", payload)
    fig = Figure(figsize=(6 * len(results), 4.2), dpi=110)
    FigureCanvasAgg(fig)
    for i, r in enumerate(results):
        ax = fig.add_subplot(1, len(results), i + 1)
        for n in r["error_mm"]:
            ax.plot(r["components"], r["error_mm"][n], marker="o", label=_model_title(n, r))
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_xticks(r["components"], [str(k) for k in r["components"]])
        ax.set_xlabel("number of components")
        ax.set_ylabel("mean vertex error (mm)")
        ax.set_title(f"Leave-one-subject-out, {_SELECTION_TITLES.get(r['selection'], r['selection'])}", fontsize=10)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(out / f"{stem}.png") as tmp:
        fig.savefig(tmp, format="png", facecolor="white", metadata=PNG_METADATA)
    return {"table": f"{stem}.md", "json": f"{stem}.json", "png": f"{stem}.png"}
