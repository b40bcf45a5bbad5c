"""Two studies of the shape space, as tables (Markdown + JSON) and PNGs.

- ``interpolation_study`` (Hasler et al. 2009, Fig. 5): halfway between every pair of scans of
  a few subjects, linear in code space, for the relative rotation encoding (RRE) and the vertex
  encoding; the halfway mesh's mean relative edge-length change and volume change against the
  endpoints' average (``shape.compare``'s definitions). RRE interpolates joint angles and keeps
  the body intact; vertex interpolation pulls rotated limbs towards the chord.
- ``generalization_study``: leave-one-subject-out reconstruction error against the number of
  PCA components, RRE against vertex PCA. For each held-out subject the PCA is fitted on every
  other subject's scans and the held-out scans are projected and reconstructed; the error is
  the mean vertex distance (mm) between the reconstruction and the scan, both in the documented
  placement (rigidly aligned to the encoder's mean model, docs/encoding.md). A second error,
  ``local_error_mm``, first aligns each of ``LOCAL_REGIONS`` body regions (k-means clusters of
  the mean scan's vertices, the same for every encoder) rigidly onto the scan: it separates the
  error of the local shape from limbs and regions that are merely turned or shifted. RRE's
  excess global error is almost all of the second kind. The code-space projection favours
  local triangle detail, and the decode (rotation solve, Poisson) integrates what is left into
  whole regions that sit in the wrong place (wrong stature, for example). This synthetic
  population is also linear in vertex space (MakeHuman targets), which favours vertex PCA.
  Measurements: docs/encoding.md, "Generalization".

Cost, and the shortcut taken: each encoder (its reference mean model, which only fixes the
coordinates codes are taken in) is fitted once on all selected scans; only the PCA is refitted
per fold. Refitting the RRE reference per fold costs ~2 s a fold (an encoding pass and a
decode) and changes the codes' origin, not the model's variability. The remaining cost is one
RRE decode (~0.2-0.4 s on 2 cores) per halfway mesh and per (held-out scan, component count);
the demo's defaults (2 subjects x 15 pairs, 6 folds x up to 5 counts) take ~15-25 s.
"""

from __future__ import annotations

import time
from itertools import combinations
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from scipy.cluster.vq import kmeans2

from bodyspace.atomic import PNG_METADATA, atomic_path, write_json
from bodyspace.errors import ParameterError
from bodyspace.mesh.alignment import rigid_procrustes
from bodyspace.mesh.geometry import boundary_loops, capped_volume
from bodyspace.report.render import contact_sheet
from bodyspace.shape.compare import edge_lengths
from bodyspace.shape.solvers import pca_full

DEFAULT_COMPONENTS = (1, 2, 4, 8, 16)
# Regions of the local error (k-means clusters of the mean scan's vertices).
LOCAL_REGIONS = 12


def _scans(db, rows) -> np.ndarray:
    """(n, V, 3) float64 scans ``rows`` of a (memory-mapped) database, read in index order."""
    rows = np.asarray(rows)
    order = np.argsort(rows, kind="stable")
    out = np.empty((len(rows),) + tuple(db.vertices.shape[1:]))
    out[order] = db.vertices[rows[order]]
    return out


def _rows_by_subject(db, rows: np.ndarray) -> dict[str, np.ndarray]:
    subj = np.asarray(db.scans["subject"])[rows]
    order = list(dict.fromkeys(subj.tolist()))
    return {s: rows[subj == s] for s in order}


# ------------------------------------------------------------------------------- interpolation

def interpolation_study(db, encoders: dict, n_subjects: int = 2, subjects: Sequence[str] | None = None,
                        progress: Callable[[str, float], None] | None = None) -> dict:
    """Halfway meshes between all pairs of scans of ``n_subjects`` subjects, per encoder.

    Args:
        db: a ``ScanDatabase``.
        encoders: {name: fitted encoder}, e.g. ``{"rre": ..., "vertex": ...}``.
        n_subjects: how many subjects (the first with at least two scans), unless ``subjects``.
    Returns:
        dict with ``rows`` (one per pair: subject, pose_a, pose_b, and per encoder
        ``{name}_edge_change`` / ``{name}_volume_change``, fractions), ``summary`` (per encoder:
        mean and max edge change, mean and max |volume change|), ``example`` (the pair with the
        largest vertex-encoding edge change: scan indices and the halfway meshes), ``cost_s``.
    """
    report = progress or (lambda m, f: None)
    t0 = time.perf_counter()
    by_subject = {s: r for s, r in _rows_by_subject(db, np.arange(db.n_scans)).items() if len(r) >= 2}
    chosen = list(subjects) if subjects is not None else list(by_subject)[:n_subjects]
    if not chosen or any(s not in by_subject for s in chosen):
        raise ParameterError(f"interpolation_study: subjects {chosen!r}; expected subjects with at least two scans "
                             f"(available: {', '.join(list(by_subject)[:10]) or 'none'})")
    pairs = [(a, b) for s in chosen for a, b in combinations(by_subject[s].tolist(), 2)]
    rows = np.unique(np.array(pairs).ravel())
    where = {int(r): k for k, r in enumerate(rows)}
    scans = _scans(db, rows)
    ia = np.array([where[a] for a, _ in pairs])
    ib = np.array([where[b] for _, b in pairs])
    faces = np.asarray(db.faces)
    loops = boundary_loops(faces)
    ref_len = 0.5 * (edge_lengths(scans[ia], faces) + edge_lengths(scans[ib], faces))
    vol = capped_volume(scans, faces, loops)
    ref_vol = 0.5 * (vol[ia] + vol[ib])
    table = [{"subject": str(db.scans["subject"][a]), "pose_a": str(db.scans["pose"][a]),
              "pose_b": str(db.scans["pose"][b]), "scan_a": int(a), "scan_b": int(b)} for a, b in pairs]
    halfway = {}
    for k, (name, enc) in enumerate(encoders.items()):
        report(f"interpolating {len(pairs)} pairs ({name})", k / len(encoders))
        codes = enc.encode(scans)
        mid = enc.decode(0.5 * (codes[ia] + codes[ib]))
        halfway[name] = mid
        edge = np.mean(np.abs(edge_lengths(mid, faces) - ref_len) / ref_len, axis=-1)
        dvol = (capped_volume(mid, faces, loops) - ref_vol) / ref_vol
        for row, e, v in zip(table, edge, dvol):
            row[f"{name}_edge_change"] = float(e)
            row[f"{name}_volume_change"] = float(v)
    summary = {name: {"edge_change_mean": float(np.mean([r[f"{name}_edge_change"] for r in table])),
                      "edge_change_max": float(np.max([r[f"{name}_edge_change"] for r in table])),
                      "volume_change_abs_mean": float(np.mean([abs(r[f"{name}_volume_change"]) for r in table])),
                      "volume_change_abs_max": float(np.max([abs(r[f"{name}_volume_change"]) for r in table]))}
               for name in encoders}
    key = "vertex" if "vertex" in encoders else next(iter(encoders))
    best = int(np.argmax([r[f"{key}_edge_change"] for r in table]))
    example = {"pair": best, "scan_a": pairs[best][0], "scan_b": pairs[best][1],
               "a": scans[ia[best]], "b": scans[ib[best]],
               "halfway": {name: m[best] for name, m in halfway.items()}}
    report("interpolation done", 1.0)
    return {"subjects": chosen, "pairs": len(pairs), "rows": table, "summary": summary, "example": example,
            "cost_s": round(time.perf_counter() - t0, 2)}


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


# ------------------------------------------------------------------------------- generalization

def generalization_study(db, encoders: dict, selection: str = "rest", n_folds: int = 6,
                         components: Sequence[int] = DEFAULT_COMPONENTS,
                         progress: Callable[[str, float], None] | None = None) -> dict:
    """Leave-one-subject-out reconstruction error (mm) against the number of components.

    Args:
        db: a ``ScanDatabase``.
        encoders: {name: fitted encoder}; each is fitted once (see the module docstring).
        selection: "rest" (shape-only model) or "all" scans.
        n_folds: held-out subjects (the first ``n_folds``; at most 8 is the intended use).
        components: component counts; each is capped at the training set's rank, and the
            largest possible count (all components) is always added.
    Returns:
        dict with ``components`` (the counts), ``error_mm`` {name: (n_counts,) mean over folds
        and held-out scans of the mean vertex distance}, ``local_error_mm`` (the same after a
        rigid alignment of each of ``LOCAL_REGIONS`` regions, see the module docstring),
        ``error_mm_per_fold``, ``folds`` (held-out subjects), ``cost_s``.
    """
    report = progress or (lambda m, f: None)
    t0 = time.perf_counter()
    if selection == "rest":
        rows = np.flatnonzero(np.asarray(db.scans["pose"]) == "rest")
    elif selection == "all":
        rows = np.arange(db.n_scans)
    else:
        raise ParameterError(f"selection={selection!r}, expected 'rest' or 'all'")
    groups = _rows_by_subject(db, rows)
    if len(groups) < 3:
        raise ParameterError(f"generalization_study: {len(groups)} subjects in selection {selection!r}, "
                             "expected at least 3")
    held_subjects = list(groups)[:max(1, min(n_folds, len(groups)))]
    subj = np.asarray(db.scans["subject"])[rows]
    scans = _scans(db, rows)
    max_k = min(len(rows) - len(groups[s]) - 1 for s in held_subjects)
    ks = sorted({int(k) for k in components if 1 <= k <= max_k} | {max_k})
    errors, per_fold, local = {}, {}, {}
    mean_scan = scans.mean(axis=0)
    _, labels = kmeans2(mean_scan, min(LOCAL_REGIONS, len(mean_scan)), seed=0, minit="++")
    regions = [np.flatnonzero(labels == c) for c in np.unique(labels)]
    for e_idx, (name, enc) in enumerate(encoders.items()):
        report(f"leave-one-subject-out ({name})", e_idx / len(encoders))
        codes = enc.encode(scans)
        targets = rigid_procrustes(scans, enc.mean_vertices_)[0]
        recon_codes, where = [], []
        for f, s in enumerate(held_subjects):
            test = subj == s
            train = codes[~test]
            mean = train.mean(axis=0)
            _, comps = pca_full(train.copy(), mean)
            z = (codes[test] - mean) @ comps.T
            for j, k in enumerate(ks):
                kk = min(k, len(comps))
                recon_codes.append(mean + z[:, :kk] @ comps[:kk])
                where.append((f, j, np.flatnonzero(test)))
        decoded = enc.decode(np.concatenate(recon_codes))
        err = np.zeros((len(held_subjects), len(ks)))
        err_local = np.zeros_like(err)
        start = 0
        for f, j, idx in where:
            dec, tgt = decoded[start:start + len(idx)], targets[idx]
            err[f, j] = 1000.0 * np.linalg.norm(dec - tgt, axis=-1).mean()
            aligned = np.empty_like(dec)
            for r in regions:
                aligned[:, r] = rigid_procrustes(dec[:, r], tgt[:, r])[0]
            err_local[f, j] = 1000.0 * np.linalg.norm(aligned - tgt, axis=-1).mean()
            start += len(idx)
        errors[name] = err.mean(axis=0).tolist()
        local[name] = err_local.mean(axis=0).tolist()
        per_fold[name] = err.tolist()
    report("generalization done", 1.0)
    return {"selection": selection, "components": ks, "folds": held_subjects, "error_mm": errors,
            "local_error_mm": local, "local_regions": len(regions),
            "error_mm_per_fold": per_fold, "training_subjects": len(groups) - 1,
            "cost_s": round(time.perf_counter() - t0, 2)}


def write_generalization_report(result: dict, out, stem: str = "generalization") -> dict:
    """Write ``{stem}.md``, ``{stem}.json`` and a ``{stem}.png`` plot into ``out``."""
    out = Path(out)
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

