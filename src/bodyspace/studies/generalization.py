"""Generalization study: leave-one-subject-out reconstruction error against the number of
PCA components, RRE against vertex PCA.

For each held-out subject the PCA is fitted on every other subject's scans and the held-out
scans are projected and reconstructed; the error is the mean vertex distance (mm) between the
reconstruction and the scan, both in the documented placement (rigidly aligned to the encoder's
mean model, docs/encoding.md). A second error, ``local_error_m``, first aligns each of
``LOCAL_REGIONS`` body regions (k-means clusters of the mean scan's vertices, the same for
every encoder) rigidly onto the scan: it separates the error of the local shape from limbs and
regions that are merely turned or shifted. RRE's excess global error is almost all of the
second kind. The code-space projection favours local triangle detail, and the decode (rotation
solve, Poisson) integrates what is left into whole regions that sit in the wrong place (wrong
stature, for example). This synthetic population is also linear in vertex space (MakeHuman
targets), which favours vertex PCA. Measurements: docs/encoding.md, "Generalization".

Cost, and the shortcut taken: each encoder (its reference mean model, which only fixes the
coordinates codes are taken in) is fitted once on all selected scans; only the PCA is refitted
per fold. Refitting the RRE reference per fold costs ~2 s a fold (an encoding pass and a
decode) and changes the codes' origin, not the model's variability. The remaining cost is one
RRE decode (~0.2-0.4 s on 2 cores) per (held-out scan, component count).
``report.shape_report.write_generalization_report`` writes the table and the plot.
"""

from __future__ import annotations

import time
from typing import Callable, Sequence

import numpy as np
from scipy.cluster.vq import kmeans2

from bodyspace.errors import ParameterError
from bodyspace.mesh.alignment import rigid_procrustes
from bodyspace.shape.solvers import pca_full
from bodyspace.studies.scans import rows_by_subject

__all__ = ["DEFAULT_COMPONENTS", "LOCAL_REGIONS", "generalization_study"]

DEFAULT_COMPONENTS = (1, 2, 4, 8, 16)
# Regions of the local error (k-means clusters of the mean scan's vertices).
LOCAL_REGIONS = 12


def generalization_study(db, encoders: dict, selection: str = "rest", n_folds: int = 6,
                         components: Sequence[int] = DEFAULT_COMPONENTS,
                         progress: Callable[[str, float], None] | None = None) -> dict:
    """Leave-one-subject-out reconstruction error (metres) against the number of components.

    Args:
        db: a ``ScanDatabase``.
        encoders: {name: fitted encoder}; each is fitted once (see the module docstring).
        selection: "rest" (shape-only model) or "all" scans.
        n_folds: held-out subjects (the first ``n_folds``; at most 8 is the intended use).
        components: component counts; each is capped at the training set's rank, and the
            largest possible count (all components) is always added.
    Returns:
        dict with ``components`` (the counts), ``error_m`` {name: (n_counts,) mean over folds
        and held-out scans of the mean vertex distance, metres}, ``local_error_m`` (the same
        after a rigid alignment of each of ``LOCAL_REGIONS`` regions, see the module docstring),
        ``error_m_per_fold`` {name: (n_folds, n_counts)}, ``folds`` (held-out subjects),
        ``cost_s``. ``report.shape_report.generalization_in_mm`` gives the same in mm.
    """
    report = progress or (lambda m, f: None)
    t0 = time.perf_counter()
    if selection == "rest":
        rows = np.flatnonzero(np.asarray(db.scans["pose"]) == "rest")
    elif selection == "all":
        rows = np.arange(db.n_scans)
    else:
        raise ParameterError(f"selection={selection!r}, expected 'rest' or 'all'")
    groups = rows_by_subject(db, rows)
    if len(groups) < 3:
        raise ParameterError(f"generalization_study: {len(groups)} subjects in selection {selection!r}, "
                             "expected at least 3")
    held_subjects = list(groups)[:max(1, min(n_folds, len(groups)))]
    subj = np.asarray(db.scans["subject"])[rows]
    scans = db.read(rows)
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
            err[f, j] = np.linalg.norm(dec - tgt, axis=-1).mean()
            aligned = np.empty_like(dec)
            for r in regions:
                aligned[:, r] = rigid_procrustes(dec[:, r], tgt[:, r])[0]
            err_local[f, j] = np.linalg.norm(aligned - tgt, axis=-1).mean()
            start += len(idx)
        errors[name] = err.mean(axis=0).tolist()
        local[name] = err_local.mean(axis=0).tolist()
        per_fold[name] = err.tolist()
    report("generalization done", 1.0)
    return {"selection": selection, "components": ks, "folds": held_subjects, "error_m": errors,
            "local_error_m": local, "local_regions": len(regions),
            "error_m_per_fold": per_fold, "training_subjects": len(groups) - 1,
            "cost_s": round(time.perf_counter() - t0, 2)}
