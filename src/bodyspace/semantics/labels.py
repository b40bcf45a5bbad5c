"""Labels of a scan database: what the semantic regressors learn (Hasler §4).

One row per subject, its rest scan (the first of a model's fitted scans for that subject), and
three kinds of labels:

- *measured* labels (``MEASURED_LABELS``: stature, mass, waist/chest/hip girth, and every other
  length of the measurement set the user's labels give): the user's own values where the
  database's subject table has them (``stature_cm``, ``mass_kg``, ``waist_girth_cm``, any
  ``<length>_cm``: a weighed mass beats a volume estimate), what a tape measure (and a scale,
  at the default density) reads on the rest scans where it has not (per subject, per label);
  during generation they are measured on every decoded body;
- *subject* labels (``SUBJECT_LABELS``: sex 1 = male / 0 = female, age, body fat %, muscle): the
  database's subject columns, only known through their regressors;
- *measurement targets*: every other length of the measurement set (Rupprecht's waist_size, ...,
  ISO thigh_girth_l, shoulder_width, ...), measured on a body only when a request names them.

``label_set`` merges them and keeps, per label, where its values came from (``provenance``), the
labels it could not learn and why (``skipped``), and the subject columns it did not use.
Functions here take arrays and the database's public attributes; nothing fits or decodes.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from bodyspace.errors import ParameterError
from bodyspace.units import format_value

__all__ = ["MEASURED_LABELS", "SUBJECT_LABELS", "MIN_LABELLED", "LABEL_COLUMN_UNITS", "first_scan_per_subject",
           "read_scans", "labels_from_subjects", "measured_labels", "measurement_targets", "measurement_subset",
           "label_columns", "LabelSet", "label_set", "describe_source"]

MEASURED_LABELS = ("stature", "mass", "waist_girth", "chest_girth", "hip_girth")
# label -> database subject column
SUBJECT_LABELS = {"sex": "sex", "age": "age_years", "body_fat": "body_fat_percent", "muscle": "muscle_1"}
# a label needs this many known, not all equal, values to get a regressor: a cross-validated
# regressor trains on 3 rows (leave-one-out) and the filtered one cross-validates inside those
MIN_LABELLED = 4
# A subject column that gives a measurement of the set: the measurement's SI unit -> (column
# suffix, factor from the column's unit to SI). Stature and every other length in cm, mass in kg.
LABEL_COLUMN_UNITS = {"m": ("_cm", 0.01), "kg": ("_kg", 1.0)}
# Other spellings of a measurement's column (the first present of the name's own and these wins;
# a column gives one label: height_cm is the person's stature, not Rupprecht's head-top height).
LABEL_COLUMN_ALIASES = {"mass": ("weight_kg",), "stature": ("height_cm",)}


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
        v = _subject_values(name, np.asarray(columns[col])[where])
        if np.isfinite(v).sum() >= MIN_LABELLED and np.nanstd(v) > 0:
            out[name] = v
    return out


def _subject_values(name: str, raw: np.ndarray) -> np.ndarray:
    """A subject label column's values (N,) as float64: ``sex`` and any text column as 1 male /
    0 female / NaN, numbers as they are."""
    if name == "sex" or raw.dtype.kind in "OUS":
        low = np.char.lower(raw.astype(str))
        return np.where(low == "male", 1.0, np.where(low == "female", 0.0, np.nan))
    return raw.astype(float)


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


# ----------------------------------------------------------------------------- the user's labels
def label_columns(mset, columns) -> dict[str, str]:
    """Measurement name -> the subject column that gives its values: ``<name>_cm`` for a length
    of measurement set ``mset`` (stature_cm, waist_girth_cm, thigh_girth_l_cm, ...; stature also
    from ``height_cm``), ``mass_kg`` (or ``weight_kg``) for mass; only columns present in
    ``columns`` (a mapping or names), each giving one measurement, in the set's order."""
    present = set(columns)
    out = {}
    for m in sorted(mset.measurements, key=lambda m: m["name"] not in LABEL_COLUMN_ALIASES):  # aliases first
        unit = LABEL_COLUMN_UNITS.get(m["unit"])
        if unit is None or (m["unit"] == "kg" and m["name"] != "mass"):
            continue
        for column in (m["name"] + unit[0],) + LABEL_COLUMN_ALIASES.get(m["name"], ()):
            if column in present and column not in out.values():
                out[m["name"]] = column
                break
    return {m["name"]: out[m["name"]] for m in mset.measurements if m["name"] in out}


@dataclass
class LabelSet:
    """What the regressors learn, one row per subject, and where each value came from.

    values: label -> (N,) float64 SI values (NaN unknown), in learning order: the measured labels,
        then the subject labels. measured: the labels measured on bodies (in ``values``).
    provenance: label -> JSON-able dict: ``kind`` ("measured" / "subject"), ``source`` (the file
        the user's values came from), ``column`` (or None), ``n`` subjects, ``from_labels``,
        ``measured`` (rest scans), ``unknown`` counts, ``unknown_why`` (the measurement's note,
        or None) and ``tape_vs_labels`` (``n``, ``mean``, ``sd`` of tape - label over the
        subjects with both, SI; or None).
    skipped: label -> why it has no regressor. unused: subject columns no label uses.
    """

    values: dict = field(default_factory=dict)
    measured: list = field(default_factory=list)
    provenance: dict = field(default_factory=dict)
    skipped: dict = field(default_factory=dict)
    unused: list = field(default_factory=list)


def label_set(mset, columns, subjects, measured_values, measured_notes=None, measured=MEASURED_LABELS,
              subject_labels=None, source: str = "subjects.csv") -> LabelSet:
    """The labels of ``subjects`` (N,) ids: user values first, measured ones fill the gaps.

    Args:
        mset: the measurement set (which names are lengths: ``label_columns``).
        columns: the database's subject table, column -> (P,) values, with ``"subject"`` ids.
        subjects: (N,) ids, one per rest scan, each in ``columns["subject"]``.
        measured_values: name -> (N,) values measured on the rest scans (SI, NaN undefined).
        measured_notes: name -> (N,) why a value is NaN (``Measurement.note``), or None.
        measured: the core measured labels; every length the columns give is added.
        subject_labels: label -> column (default ``SUBJECT_LABELS``).
        source: the name the user knows the columns by (their labels CSV).
    Returns:
        ``LabelSet``; a label with fewer than ``MIN_LABELLED`` known or all-equal values is in
        ``skipped`` (with the counts and the measurement's note), not in ``values``.
    """
    ids = np.asarray(columns["subject"]).astype(str)
    index = {s: i for i, s in enumerate(ids)}
    missing = [s for s in subjects if s not in index]
    if missing:
        raise ParameterError(f"database: subjects {missing[:3]} of the scans are not in its subject table")
    where = np.array([index[s] for s in subjects], dtype=np.int64)
    n = len(where)
    given = label_columns(mset, columns)
    si_unit = {m["name"]: m["unit"] for m in mset.measurements}
    names = [m for m in measured if m in measured_values] + [m["name"] for m in mset.measurements
                                                              if m["name"] in given and m["name"] not in measured]
    unknown_names = [m for m in measured if m not in measured_values]
    if unknown_names:
        raise ParameterError(f"measured labels {unknown_names} are not in the measurement set; expected names from "
                             f"{', '.join(measured_values)}")
    out = LabelSet()
    for name in names:
        tape = np.asarray(measured_values[name], dtype=float)
        column = given.get(name)
        user = np.full(n, np.nan)
        if column is not None:
            user = np.asarray(columns[column], dtype=float)[where] * LABEL_COLUMN_UNITS[si_unit[name]][1]
        has_user, has_tape = np.isfinite(user), np.isfinite(tape)
        y = np.where(has_user, user, tape)
        both = has_user & has_tape
        notes = [] if measured_notes is None else [measured_notes[name][i] for i in range(n)
                                                   if not has_user[i] and not has_tape[i] and measured_notes[name][i]]
        out.provenance[name] = {
            "kind": "measured", "source": source, "column": column, "n": n,
            "from_labels": int(has_user.sum()), "measured": int((~has_user & has_tape).sum()),
            "unknown": int((~has_user & ~has_tape).sum()),
            "unknown_why": _common_note(notes),
            "tape_vs_labels": ({"n": int(both.sum()), "mean": float(np.mean(tape[both] - user[both])),
                                "sd": float(np.std(tape[both] - user[both]))} if both.any() else None)}
        reason = _unlearnable(y)
        if reason:
            out.skipped[name] = f"{reason} ({describe_source(name, out.provenance[name], short=True)})"
            continue
        out.values[name] = y
        out.measured.append(name)
    for name, column in (SUBJECT_LABELS if subject_labels is None else subject_labels).items():
        if column not in columns:
            continue
        v = _subject_values(name, np.asarray(columns[column])[where])
        known = np.isfinite(v)
        out.provenance[name] = {"kind": "subject", "source": source, "column": column, "n": n,
                                "from_labels": int(known.sum()), "measured": 0, "unknown": int((~known).sum()),
                                "unknown_why": None, "tape_vs_labels": None}
        reason = _unlearnable(v)
        if reason:
            out.skipped[name] = f"{reason} ({describe_source(name, out.provenance[name], short=True)})"
            continue
        out.values[name] = v
    used = {"subject", "sex", *given.values(), *(SUBJECT_LABELS if subject_labels is None else subject_labels).values()}
    out.unused = [c for c in columns if c not in used]
    return out


def _unlearnable(y: np.ndarray) -> str | None:
    """Why a label (N,) gets no regressor, or None: too few known values, or all equal."""
    known = np.isfinite(y)
    if known.sum() < MIN_LABELLED:
        return f"known on {int(known.sum())} of {len(y)} subjects, at least {MIN_LABELLED} needed"
    if np.ptp(y[known]) == 0:
        return f"every known value is {y[known][0]:g}, nothing to learn"
    return None


def _common_note(notes: list) -> str | None:
    """The most frequent of the measurements' notes, with how many subjects share it."""
    if not notes:
        return None
    kinds = {}
    for note in notes:
        kinds.setdefault(str(note).split(":")[0], []).append(str(note))
    head, group = max(kinds.items(), key=lambda item: len(item[1]))
    more = f"; {len(notes) - len(group)} other reason(s)" if len(group) < len(notes) else ""
    return f"{group[0]} ({len(group)} subject(s){more})" if len(notes) > 1 else group[0]


def describe_source(name: str, p: dict, short: bool = False) -> str:
    """Where a label's values came from, for people: ``"labels.csv (10 of 10 subjects)"``,
    ``"measured on the rest scans (10 of 10 subjects)"``, ``"labels.csv 7, measured on the rest
    scans 3 (of 10 subjects)"``, then the unknown ones and why, and (not ``short``) how far the
    tape on the rest scans is from the user's values."""
    n, given, tape, unknown = p["n"], p["from_labels"], p["measured"], p["unknown"]
    user = f"{p['source']}" + (f" column {p['column']}" if not short and p.get("column") else "")
    if given and not tape:
        text = f"{user} ({given} of {n} subjects)"
    elif tape and not given:
        text = f"measured on the rest scans ({tape} of {n} subjects)"
    elif given and tape:
        text = f"{user} {given}, measured on the rest scans {tape} (of {n} subjects)"
    else:
        text = f"no value for any of {n} subjects"
    if unknown and (given or tape):
        text += f", unknown {unknown}"
    if unknown and p.get("unknown_why"):
        text += f" ({p['unknown_why']})"
    agree = p.get("tape_vs_labels")
    if not short and agree and agree["n"]:
        text += (f"; tape on the rest scans - {p['source']}: mean {_signed(name, agree['mean'])}, SD "
                 f"{format_value(name, agree['sd'])} ({agree['n']} subjects with both)")
    return text


def _signed(name: str, value: float) -> str:
    """``+0.22 kg``, ``-1.3 cm``; no sign on a value that shows as zero."""
    text = format_value(name, abs(value))
    if not any(ch in "123456789" for ch in text.split()[0]):
        return text
    return ("+" if value >= 0 else "-") + text
