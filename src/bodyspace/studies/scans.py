"""Scan selection shared by the shape studies: rows of a database grouped by subject (the rows
themselves are read by ``ScanDatabase.read``)."""

from __future__ import annotations

import numpy as np


def rows_by_subject(db, rows: np.ndarray) -> dict[str, np.ndarray]:
    """{subject: its rows among ``rows`` (n,)}, subjects in order of first appearance."""
    subj = np.asarray(db.scans["subject"])[rows]
    order = list(dict.fromkeys(subj.tolist()))
    return {s: rows[subj == s] for s in order}
