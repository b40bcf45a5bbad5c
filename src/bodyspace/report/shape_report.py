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
    ``error_mm_per_fold`` in place of the ``*_m`` fields (metres); everything else as it is."""
    keys = {"error_m": "error_mm", "local_error_m": "local_error_mm", "error_m_per_fold": "error_mm_per_fold"}
    out = {}
    for k, v in result.items():
        if k in keys:
            out[keys[k]] = {name: (1000.0 * np.asarray(e, dtype=float)).tolist() for name, e in v.items()}
        else:
            out[k] = v
    return out


def write_generalization_report(result: dict, out, stem: str = "generalization") -> dict:
    """Write ``{stem}.md``, ``{stem}.json`` (errors in mm) and a ``{stem}.png`` plot into ``out``."""
    out = Path(out)
    result = generalization_in_mm(result)
    names = list(result["error_mm"])
    lines = [f"# Leave-one-subject-out reconstruction error ({result['selection']} scans, "
             f"{len(result['folds'])} held-out subjects)", "",
             "Mean vertex distance (mm) between a held-out scan and its reconstruction from the first k "
             "components, both rigidly aligned to the encoder's mean model; \"local\": the same after "
             f"aligning each of {result.get('local_regions', '?')} body regions rigidly (turned or shifted limbs "
             "removed, docs/encoding.md, \"Generalization\").", "",
             "| k | " + " | ".join(f"{n} (mm)" for n in names) + " | "
             + " | ".join(f"{n} local (mm)" for n in names) + " |", "|---|" + "---|" * (2 * len(names))]
    local = result.get("local_error_mm", {})
    for j, k in enumerate(result["components"]):
        lines.append(f"| {k} | " + " | ".join(f"{result['error_mm'][n][j]:.2f}" for n in names) + " | "
                     + " | ".join(f"{local[n][j]:.2f}" if n in local else "-" for n in names) + " |")
    with atomic_path(out / f"{stem}.md") as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    write_json(out / f"{stem}.json", {**result, "units": {"error": "mm"}})
    fig = Figure(figsize=(6, 4), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    for n in names:
        ax.plot(result["components"], result["error_mm"][n], marker="o", label=n)
    ax.set_xlabel("number of components")
    ax.set_ylabel("mean vertex error (mm)")
    ax.set_title(f"Leave-one-subject-out, {result['selection']} scans")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    with atomic_path(out / f"{stem}.png") as tmp:
        fig.savefig(tmp, format="png", facecolor="white", metadata=PNG_METADATA)
    return {"table": f"{stem}.md", "json": f"{stem}.json", "png": f"{stem}.png"}
