"""Scan selection shared by the shape studies: rows of a database read in bulk, grouped by subject."""

from __future__ import annotations

import numpy as np


def read_scans(db, rows) -> np.ndarray:
    """(n, V, 3) float64 scans ``rows`` (n,) of a (memory-mapped) database, in the order given.

    The rows are read in index order (sequential reads of the memory map) and put back."""
    rows = np.asarray(rows)
    order = np.argsort(rows, kind="stable")
    out = np.empty((len(rows),) + tuple(db.vertices.shape[1:]))
    out[order] = db.vertices[rows[order]]
    return out


def rows_by_subject(db, rows: np.ndarray) -> dict[str, np.ndarray]:
    """{subject: its rows among ``rows`` (n,)}, subjects in order of first appearance."""
    subj = np.asarray(db.scans["subject"])[rows]
    order = list(dict.fromkeys(subj.tolist()))
    return {s: rows[subj == s] for s in order}
