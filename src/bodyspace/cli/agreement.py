"""``bodyspace agreement METHOD.csv REFERENCE.csv``: a measuring method against a reference over
a sample of subjects, as ISO 20685-1 evaluates it (``measure.agreement``; docs/measurements.md).

Both files have one row per subject: an id column (``--id``, default the first column) and one
column per measurement, named ``NAME_cm`` (or ``_mm``, ``_m``: lengths) or ``NAME_kg``,
``NAME_m3``, ... (held to 1 % of the reference: no ISO figure), as ``bodyspace measure DB --csv``
writes them. Subjects are matched by id; an empty cell is a measurement that subject lacks.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import List, Optional

import numpy as np
import typer

from bodyspace.atomic import write_json
from bodyspace.cli.common import ForceOption, check_file_output, console
from bodyspace.errors import ParameterError
from bodyspace.measure.agreement import agreement as protocol
from bodyspace.measure.agreement import format_agreement
from bodyspace.measure.definitions import load_measurement_set
from bodyspace.measure.tolerances import ALLOWABLE_ERROR, NO_ISO, iso_categories

# Length columns: suffix → metres per unit.
LENGTH_SUFFIXES = {"_cm": 0.01, "_mm": 0.001, "_m": 1.0}
# Category short names for --category (and the full ones of tolerances.ALLOWABLE_ERROR).
SHORT = {"height": "body height", "small": "small circumference", "large": "large circumference",
         "breadth": "body breadth", "depth": "body depth", "segment": "segment length", "none": NO_ISO}


def _read(path: Path, id_column: str | None) -> tuple[str, dict[str, dict[str, str]]]:
    """(id column, subject id → column → cell) of one CSV file."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            rows = list(csv.reader(fh))
    except UnicodeDecodeError as exc:
        raise ParameterError(f"{path}: not a UTF-8 text file ({exc}); expected a CSV of one row per subject") from None
    if len(rows) < 2:
        raise ParameterError(f"{path}: {len(rows)} line(s); expected a header and one row per subject")
    header = [h.strip() for h in rows[0]]
    key = id_column or header[0]
    if key not in header:
        raise ParameterError(f"{path}: no column {key!r} (--id); its columns are {', '.join(header)}")
    k = header.index(key)
    out = {}
    for line, row in enumerate(rows[1:], start=2):
        if not any(c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise ParameterError(f"{path} line {line}: {len(row)} cells; expected {len(header)} as in the header")
        subject = row[k].strip()
        if subject in out:
            raise ParameterError(f"{path} line {line}: subject {subject!r} twice; expected one row per subject")
        out[subject] = {h: c.strip() for h, c in zip(header, row) if h != key}
    return key, out


def _number(text: str, where: str) -> float:
    if text == "":
        return float("nan")
    try:
        return float(text)
    except ValueError:
        raise ParameterError(f"{where}: {text!r} is not a number; expected a value or an empty cell") from None


def _base(column: str) -> tuple[str, float | None]:
    """(measurement name, metres per unit or None when the column is not a length)."""
    for suffix, scale in LENGTH_SUFFIXES.items():
        if column.endswith(suffix):
            return column[: -len(suffix)], scale
    return column.rsplit("_", 1)[0] if "_" in column else column, None


def agreement(method: Path = typer.Argument(..., help="CSV of the method's values (e.g. scan-derived), one row "
                                            "per subject."),
              reference: Path = typer.Argument(..., help="CSV of the reference values (e.g. a skilled "
                                               "anthropometrist's tape), the same columns."),
              id_column: Optional[str] = typer.Option(None, "--id", help="The subject id column of both files "
                                                      "(default: the first column)."),
              category: Optional[List[str]] = typer.Option(None, "--category", help="NAME=CATEGORY for a "
                                                           "measurement the shipped set does not name: height, "
                                                           "small, large, breadth, depth, segment or none (1 %); "
                                                           "repeatable."),
              out: Optional[Path] = typer.Option(None, "--out", help="Also write the verdicts to this JSON file "
                                                 "(lengths in cm)."),
              force: bool = ForceOption):
    """A method's measurements against a reference's over a sample of subjects, as ISO 20685-1 evaluates
    them: per measurement the mean error, its 95 % confidence interval and whether it lies within the
    maximum allowable error."""
    if out is not None:
        check_file_output(out, "--out", force, (".json",), example="agreement.json")
    key, got = _read(method, id_column)
    _, ref = _read(reference, key if id_column is None else id_column)
    subjects = [s for s in got if s in ref]
    if len(subjects) < 2:
        raise ParameterError(f"{method} and {reference} share {len(subjects)} subject id(s) in column {key!r}; "
                             "expected at least 2 (the same ids in both files)")
    columns = [c for c in next(iter(got.values())) if c in next(iter(ref.values()))]
    if not columns:
        raise ParameterError(f"{method} and {reference} have no measurement column in common; expected the same "
                             "column names (e.g. waist_girth_cm)")
    shipped = iso_categories(load_measurement_set())
    given = {}
    for item in category or []:
        name, _, cat = item.partition("=")
        cat = SHORT.get(cat.strip().lower(), cat.strip().lower())
        if not name or cat not in ALLOWABLE_ERROR:
            raise ParameterError(f"--category {item!r}: expected NAME=CATEGORY, the category one of "
                                 f"{', '.join(SHORT)}")
        given[name.strip()] = cat
    names, cats, scales = [], [], []
    for c in columns:
        name, scale = _base(c)
        cat = given.get(c) or given.get(name) or shipped.get(name)
        if cat is None:
            raise ParameterError(f"column {c!r}: {name!r} is not a measurement of the shipped set, so its ISO 20685-1 "
                                 f"category is unknown; give it: --category {name}=large (or height, small, breadth, "
                                 "depth, segment, none)")
        if scale is None and not ALLOWABLE_ERROR[cat][1]:
            raise ParameterError(f"column {c!r}: a {cat} is a length; expected the column named with its unit "
                                 f"({name}_cm, {name}_mm or {name}_m)")
        names.append(name)
        cats.append(cat)
        scales.append(1.0 if scale is None else scale)
    values = np.array([[_number(got[s][c], f"{method} subject {s!r} column {c!r}") for c in columns]
                       for s in subjects]) * scales
    truth = np.array([[_number(ref[s][c], f"{reference} subject {s!r} column {c!r}") for c in columns]
                      for s in subjects]) * scales
    rows = protocol(values - truth, names, cats, reference=truth)
    only = sorted(set(got) ^ set(ref))
    console.print(f"{len(subjects)} subjects in both files" + (f" ({len(only)} in one only, left out: "
                                                                f"{', '.join(only[:5])}{' ...' if len(only) > 5 else ''})"
                                                                if only else ""), highlight=False)
    console.print(format_agreement(rows, length_unit="cm"), highlight=False, soft_wrap=True)
    if out is not None:
        write_json(out, {"written_by": "bodyspace", "standard": "ISO 20685-1:2018, 95 % confidence interval of the "
                         "mean error within the maximum allowable error", "subjects": len(subjects),
                         "measurements": [{"name": r.name, "category": r.category, "n": r.n,
                                           "unit": "%" if r.relative else "cm",
                                           # metres → cm, a share → %: both times 100
                                           **{k: (None if not np.isfinite(v) else round(100.0 * float(v), 4))
                                              for k, v in (("mean", r.mean), ("sd", r.sd), ("ci_low", r.ci_low),
                                                           ("ci_high", r.ci_high), ("allowable", r.allowable))},
                                           "accepted": r.accepted, "reason": r.reason} for r in rows]})
        console.print(f"wrote {out}", highlight=False)
