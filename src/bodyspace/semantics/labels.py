"""Labels of a scan database: what the semantic regressors learn (Hasler §4).

One row per subject, its rest scan (the first of a model's fitted scans for that subject), and
three kinds of labels:

- *measured* labels (``MEASURED_LABELS``: stature, mass, waist/chest/hip girth): what a tape
  measure (and a scale, at the default density) reads on the rest scans; during generation they
  are measured again on every decoded body;
- *subject* labels (``SUBJECT_LABELS``: sex 1 = male / 0 = female, age, body fat %, muscle): the
  database's subject columns, only known through their regressors;
- *measurement targets*: every other length of the measurement set (Rupprecht's waist_size, ...,
  ISO thigh_girth_l, shoulder_width, ...), measured on a body only when a request names them.

Functions here take arrays and the database's public attributes; nothing fits or decodes.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from bodyspace.errors import ParameterError

__all__ = ["MEASURED_LABELS", "SUBJECT_LABELS", "MIN_LABELLED", "first_scan_per_subject", "read_scans",
           "labels_from_subjects", "measured_labels", "measurement_targets", "measurement_subset"]

MEASURED_LABELS = ("stature", "mass", "waist_girth", "chest_girth", "hip_girth")
# label -> database subject column
SUBJECT_LABELS = {"sex": "sex", "age": "age_years", "body_fat": "body_fat_percent", "muscle": "muscle_1"}
# a label needs this many known, not all equal, values to get a regressor
MIN_LABELLED = 4


def first_scan_per_subject(subject_of_scan, fitted_scans) -> tuple[np.ndarray, np.ndarray]:
    """Rows (N,) int64 of the first fitted scan of every subject, in the order of
    ``fitted_scans``, and their subject ids (N,) str.

    Args:
        subject_of_scan: (S,) subject id of every scan of the database.
        fitted_scans: (M,) rows of the database a model was fitted on.
    """
    rows = np.asarray(fitted_scans, dtype=np.int64)
    if rows.size == 0:
        raise ParameterError("body_model: no fitted_scans recorded, expected a BodyModel from BodyModel.fit")
    subjects = np.asarray(subject_of_scan)[rows]
    _, first = np.unique(subjects, return_index=True)
    first = np.sort(first)
    if len(first) < MIN_LABELLED:
        raise ParameterError(f"database: {len(first)} subjects, expected at least {MIN_LABELLED} to fit semantic "
                             "regressors")
    return rows[first], subjects[first].astype(str)


def read_scans(db, rows) -> np.ndarray:
    """(n, V, 3) float64 scans ``rows`` (n,) of a ``ScanDatabase``, in the order asked: the
    database's own reader, ``db.read``."""
    return db.read(rows)


def labels_from_subjects(columns, subjects, labels=None) -> dict[str, np.ndarray]:
    """Subject labels (N,) float of ``subjects`` (N,) str from the database's subject columns.

    Args:
        columns: mapping column -> (P,) values, with a ``"subject"`` id column (``db.subjects``).
        subjects: (N,) the ids to label, each in ``columns["subject"]``.
        labels: label -> column (default ``SUBJECT_LABELS``); a column the database lacks is
            skipped, and so is a label with fewer than ``MIN_LABELLED`` known or all-equal values.
    Returns:
        label -> (N,) float64 values; ``sex`` (and any text column) as 1 male / 0 female / NaN.
    """
    ids = np.asarray(columns["subject"]).astype(str)
    index = {s: i for i, s in enumerate(ids)}
    missing = [s for s in subjects if s not in index]
    if missing:
        raise ParameterError(f"database: subjects {missing[:3]} of the scans are not in its subject table")
    where = np.array([index[s] for s in subjects], dtype=np.int64)
    out = {}
    for name, col in (SUBJECT_LABELS if labels is None else labels).items():
        if col not in columns:
            continue
        raw = np.asarray(columns[col])[where]
        if name == "sex" or raw.dtype.kind in "OUS":
            low = np.char.lower(raw.astype(str))
            v = np.where(low == "male", 1.0, np.where(low == "female", 0.0, np.nan))
        else:
            v = raw.astype(float)
        if np.isfinite(v).sum() >= MIN_LABELLED and np.nanstd(v) > 0:
            out[name] = v
    return out


def measured_labels(values: dict, measured=MEASURED_LABELS) -> dict[str, np.ndarray]:
    """The measured labels (N,) float of ``values`` (name -> (N,) measurements of the rest scans)."""
    unknown = [m for m in measured if m not in values]
    if unknown:
        raise ParameterError(f"measured labels {unknown} are not in the measurement set; expected names from "
                             f"{', '.join(values)}")
    return {m: np.asarray(values[m], dtype=float) for m in measured}


def measurement_targets(mset, values: dict, exclude=()) -> dict[str, np.ndarray]:
    """Every other length of measurement set ``mset`` as a target: name -> (N,) values of the
    rest scans, in the set's order; lengths in ``exclude`` (the labels) and lengths with fewer
    than ``MIN_LABELLED`` finite or all-equal values are left out."""
    out = {}
    for m in mset.measurements:
        name = m["name"]
        if name in exclude or m["unit"] != "m" or name not in values:
            continue
        y = np.asarray(values[name], dtype=float)
        ok = np.isfinite(y)
        if ok.sum() >= MIN_LABELLED and np.std(y[ok]) > 0:
            out[name] = y
    return out


def measurement_subset(mset, names):
    """The measurement set ``mset`` cut to ``names`` and what they depend on (mass needs
    stature, bmi mass and stature), in the set's order. The closed loop measures only what a
    request needs: the full set costs several times as much."""
    by_name = {m["name"]: m for m in mset.measurements}
    need, todo = set(), list(names)
    while todo:
        n = todo.pop()
        if n in need or n not in by_name:
            continue
        need.add(n)
        m = by_name[n]
        if m["method"] in ("mass", "bmi"):
            todo += [m[k] for k in ("stature", "mass") if isinstance(m.get(k), str)]
    return dataclasses.replace(mset, measurements=tuple(m for m in mset.measurements if m["name"] in need))
