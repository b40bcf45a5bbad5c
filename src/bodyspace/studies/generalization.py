"""Generalization study: leave-one-subject-out reconstruction error against the number of
PCA components, for each encoder and each way of projecting a mesh on its shape space.

For each held-out subject the PCA is fitted on every other subject's scans and the held-out
scans are projected and reconstructed. Encoders whose decoder is not affine (RRE) are measured
with both projections of ``ShapeSpace.project``: the code projection (``"code"``: encode,
project the code on the components) and the vertex-space fit through the decoder (``"vertex"``,
``shape.vertex_fit``, warm-started from the code projection); for the vertex encoding the two
are one. The error is the mean vertex distance (mm) between the reconstruction and the scan
after aligning the scan rigidly onto the reconstruction (each connected part; the same for every
model). A second error, ``local_error_m``, first aligns each of ``LOCAL_REGIONS`` body regions
(k-means clusters of the mean scan's vertices, the same for every encoder) rigidly onto the
scan: it separates the error of the local shape from limbs and regions that are merely turned
or shifted. The code projection of RRE codes favours local triangle detail, and the decode
(rotation solve, Poisson) integrates what is left into whole regions that sit in the wrong
place (wrong stature, limbs in another pose); the vertex fit removes most of that.
Measurements: docs/encoding.md, "Generalization".

Cost, and the shortcut taken: each encoder (its reference mean model, which only fixes the
coordinates codes are taken in) is fitted once on all selected scans; only the PCA is refitted
per fold. Refitting the RRE reference per fold costs ~2 s a fold (an encoding pass and a
decode) and changes the codes' origin, not the model's variability. The code projection costs
one RRE decode (~0.05-0.3 s on 2 cores) per (held-out scan, component count); the vertex fit
up to ``max_iter`` decodes and ``max_jacobians`` Jacobians of k tangent directions each
(``fit_s`` in the result: mean seconds per mesh and component count).
``report.shape_report.write_generalization_report`` writes the table and the plot.
"""

from __future__ import annotations

import time
from typing import Callable, Sequence

import numpy as np
from scipy.cluster.vq import kmeans2

from bodyspace.errors import ParameterError
from bodyspace.mesh.alignment import rigid_procrustes
from bodyspace.mesh.topology import vertex_components
from bodyspace.shape import BASES, PROJECTIONS, ShapeSpace
from bodyspace.shape.vertex_fit import MAX_ITER, MAX_JACOBIANS, align_parts, fit_coefficients
from bodyspace.studies.scans import rows_by_subject

__all__ = ["DEFAULT_COMPONENTS", "LOCAL_REGIONS", "generalization_study", "model_names"]

DEFAULT_COMPONENTS = (1, 4, 8, 16, 32)
# Regions of the local error (k-means clusters of the mean scan's vertices).
LOCAL_REGIONS = 12


def model_names(encoders: dict, projections=PROJECTIONS, bases=("code",)) -> dict[str, tuple[str, str, str]]:
    """{result key: (encoder name, projection, basis)}: ``"<name>"`` for an affine decoder (one
    projection, its two bases are one), otherwise ``"<name> <projection>"`` for each asked
    projection of the code-ordered basis and ``"<name> vertex-basis <projection>"`` of the
    vertex-ordered one (``ShapeSpace(basis=...)``)."""
    out = {}
    for name, enc in encoders.items():
        if getattr(enc, "is_linear", False):
            out[name] = (name, "code", "code")
            continue
        for b in [b for b in BASES if b in bases]:
            for p in sorted(projections, key=list(PROJECTIONS)[::-1].index):  # code projection first
                out[f"{name} {p}" if b == "code" else f"{name} {b}-basis {p}"] = (name, p, b)
    return out


def generalization_study(db, encoders: dict, selection: str = "rest", n_folds: int = 6,
                         components: Sequence[int] = DEFAULT_COMPONENTS, projections: Sequence[str] = PROJECTIONS,
                         max_iter: int = MAX_ITER, max_jacobians: int = MAX_JACOBIANS,
                         with_all_components: bool = True, bases: Sequence[str] = ("code",),
                         progress: Callable[[str, float], None] | None = None) -> dict:
    """Leave-one-subject-out reconstruction error (metres) against the number of components.

    Args:
        db: a ``ScanDatabase``.
        encoders: {name: fitted encoder}; each is fitted once (see the module docstring).
        selection: "rest" (the database's rest-pose scans: a shape-only model) or "all" scans.
        n_folds: held-out subjects (the first ``n_folds``; at most 8 is the intended use).
        components: component counts; each is capped at the training set's rank.
        bases: for encoders that are not affine, the component orders to measure
            (``ShapeSpace``'s ``basis``: "code", "vertex").
        with_all_components: also measure the largest possible count (all components). The
            vertex fit's cost grows with the count (one tangent direction per component in
            each Jacobian): at ~140 components of a posed study it is most of the study's time.
        projections: for encoders that are not affine, the projections to measure ("code",
            "vertex"); max_iter, max_jacobians: the vertex fit's budget per mesh
            (``shape.vertex_fit.fit_coefficients``).
    Returns:
        dict with ``components`` (the counts), ``models`` {key: {"encoder", "projection", "basis"}}
        (``model_names``), ``error_m`` {key: (n_counts,) mean over folds and held-out scans of
        the mean vertex distance, metres}, ``local_error_m`` (the same after a rigid alignment
        of each of ``LOCAL_REGIONS`` regions, see the module docstring), ``max_error_m`` {key:
        (n_counts,) the largest vertex distance over all held-out scans}, ``error_m_per_fold``
        {key: (n_folds, n_counts)}, ``fit_s`` {key: (n_counts,) seconds per mesh of the
        projection and decode}, ``folds`` (held-out subjects), ``cost_s``.
        ``report.shape_report.generalization_in_mm`` gives the same in mm.
    """
    report = progress or (lambda m, f: None)
    t0 = time.perf_counter()
    if selection == "rest":
        rows = np.asarray(db.rest_rows(), dtype=np.int64)
    elif selection == "all":
        rows = np.arange(db.n_scans)
    else:
        raise ParameterError(f"selection={selection!r}, expected 'rest' or 'all'")
    unknown = [p for p in projections if p not in PROJECTIONS]
    if unknown or not projections:
        raise ParameterError(f"projections={list(projections)!r}, expected some of {', '.join(PROJECTIONS)}")
    groups = rows_by_subject(db, rows)
    if len(groups) < 3:
        raise ParameterError(f"generalization_study: {len(groups)} subjects in selection {selection!r}, "
                             "expected at least 3")
    held_subjects = list(groups)[:max(1, min(n_folds, len(groups)))]
    subj = np.asarray(db.scans["subject"])[rows]
    scans = np.asarray(db.read(rows), dtype=float)
    max_k = min(len(rows) - len(groups[s]) - 1 for s in held_subjects)
    ks = sorted({int(k) for k in components if 1 <= k <= max_k} | ({max_k} if with_all_components else set()))
    if not ks:
        raise ParameterError(f"components={list(components)!r}: none between 1 and the training set's rank "
                             f"{max_k}, and with_all_components=False")
    if not bases or any(b not in BASES for b in bases):
        raise ParameterError(f"bases={list(bases)!r}, expected some of {', '.join(BASES)}")
    models = model_names(encoders, projections, bases)
    errors, per_fold, local, worst, fit_s = {}, {}, {}, {}, {}
    mean_scan = scans.mean(axis=0)
    _, labels = kmeans2(mean_scan, min(LOCAL_REGIONS, len(mean_scan)), seed=0, minit="++")
    regions = [np.flatnonzero(labels == c) for c in np.unique(labels)]
    n_work = len(held_subjects) * len(models)
    done = 0
    for name, enc in encoders.items():
        keys = [key for key, (e, _, _) in models.items() if e == name]
        codes = enc.encode(scans)
        n_parts, part_of = vertex_components(enc.faces, enc.n_vertices)
        parts = [np.flatnonzero(part_of == c) for c in range(n_parts)]
        err = {key: np.zeros((len(held_subjects), len(ks))) for key in keys}
        err_local = {key: np.zeros_like(err[key]) for key in keys}
        err_max = {key: np.zeros_like(err[key]) for key in keys}
        seconds = {key: np.zeros_like(err[key]) for key in keys}
        for f, s in enumerate(held_subjects):
            test = subj == s
            spaces = {b: ShapeSpace(enc, n_components=max_k, solver="full", basis=b).fit(codes[~test],
                                                                                         vertices=scans[~test])
                      for b in {models[key][2] for key in keys}}
            z_codes = {b: space.transform(codes[test]) for b, space in spaces.items()}
            for key in keys:
                space, z_code = spaces[models[key][2]], z_codes[models[key][2]]
                report(f"leave-one-subject-out ({key}, subject {s})", done / n_work)
                done += 1
                for j, k in enumerate(ks):
                    t = time.perf_counter()
                    z = z_code.copy()
                    z[:, k:] = 0.0
                    if models[key][1] == "vertex":
                        z = fit_coefficients(space, scans[test], k, start=z, max_iter=max_iter,
                                             max_jacobians=max_jacobians).coefficients
                    decoded = space.reconstruct(z)
                    seconds[key][f, j] = (time.perf_counter() - t) / int(test.sum())
                    tgt = np.array([align_parts(y, x, parts) for y, x in zip(scans[test], decoded)])
                    dist = np.linalg.norm(decoded - tgt, axis=-1)
                    err[key][f, j] = dist.mean()
                    err_max[key][f, j] = dist.max()
                    aligned = np.empty_like(decoded)
                    for r in regions:
                        aligned[:, r] = rigid_procrustes(decoded[:, r], tgt[:, r])[0]
                    err_local[key][f, j] = np.linalg.norm(aligned - tgt, axis=-1).mean()
        for key in keys:
            errors[key] = err[key].mean(axis=0).tolist()
            local[key] = err_local[key].mean(axis=0).tolist()
            worst[key] = err_max[key].max(axis=0).tolist()
            per_fold[key] = err[key].tolist()
            fit_s[key] = seconds[key].mean(axis=0).tolist()
    report("generalization done", 1.0)
    return {"selection": selection, "components": ks, "folds": held_subjects,
            "models": {key: {"encoder": e, "projection": p, "basis": b} for key, (e, p, b) in models.items()},
            "error_m": errors, "local_error_m": local, "max_error_m": worst, "local_regions": len(regions),
            "error_m_per_fold": per_fold, "fit_s": fit_s, "training_subjects": len(groups) - 1,
            "held_out_scans": int(sum(len(groups[s]) for s in held_subjects)),
            "vertex_fit": {"max_iter": int(max_iter), "max_jacobians": int(max_jacobians)},
            "cost_s": round(time.perf_counter() - t0, 2)}
