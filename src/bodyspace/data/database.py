"""The scan database: registered meshes of many subjects in many poses, with per-subject labels.

Both papers start here. Every scan shares one topology (same vertex count, same faces, same
vertex *index* for the same point of the body), so the whole set is one array (N, V, 3).

On disk a database is a folder (``FORMAT_VERSION = 1``)::

    vertices.npy    (N_scans, V, 3) float32, opened with mmap_mode="r" (lazy: 2,000 scans stay on disk)
    faces.npy       (F, 3) int32
    subjects.csv    one row per subject: ``subject`` id, optional ``sex`` (female/male), and
                    numeric labels whose name ends in their unit (``height_cm``, ``bmi_kg_m2``...)
    scans.csv       one row per scan, in the order of vertices.npy: ``scan``, ``subject``, ``pose``
    rotations.npy   optional (N_scans, J, 3) float32 axis-angle joint rotations that posed each scan
    meta.json       format_version, template, units, provenance, licence, n_scans, n_vertices,
                    n_faces, and ``joints`` (J names) when rotations.npy is present

No pickle anywhere: arrays are read with ``allow_pickle=False``, tables are CSV, metadata JSON.
Vertex coordinates are in metres; label units are in the column names and are kept as written.
"""

from __future__ import annotations

import csv
import json
import math
import os
import re
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Mapping

import numpy as np

from bodyspace.atomic import atomic_dir, atomic_path, check_replaceable_folder
from bodyspace.rowfile import create_rows, npy_layout, read_rows, write_rows
from bodyspace.errors import BodyspaceError, DatabaseError
from bodyspace.measure.conventions import BODY_EXTENT_M, UP_ROTATIONS
from bodyspace.mesh.io import load_mesh

FORMAT_VERSION = 1
REST_POSE = "rest"
# meta.json field naming the rest pose of an imported database: {"pose": NAME} (the scans of that
# pose) or {"first": true} (each subject's first scan, in file order). Absent: pose REST_POSE.
REST_POSE_FIELD = "rest_pose"
REST_POSE_FIRST = "first"

# Label column suffix -> unit. "_kg_m2" (BMI) also ends in "_m2"; unit_of_label tries the
# longest suffix first so BMI is not read as an area.
LABEL_UNITS = {
    "_kg_m2": "kg/m^2",
    "_cm": "cm",
    "_kg": "kg",
    "_m3": "m^3",
    "_m2": "m^2",
    "_years": "years",
    "_percent": "%",
    "_1": "1",
}
# Labels implausible for a human are refused when meshes are imported (read_mesh_folder): one
# table, name -> (lowest, highest) in the unit of the name's suffix. A name not listed here is
# checked by its unit (UNIT_RANGES). Wide on purpose: infants to the tallest and heaviest adults;
# the point is to catch a wrong unit (1.70 for stature in cm, grams for kg) or a sign.
PLAUSIBLE_LABELS = {
    "stature_cm": (40.0, 280.0),
    "height_cm": (40.0, 280.0),
    "target_stature_cm": (40.0, 280.0),
    "mass_kg": (2.0, 650.0),
    "weight_kg": (2.0, 650.0),
    "bmi_kg_m2": (8.0, 120.0),
    "target_bmi_kg_m2": (8.0, 120.0),
    "age_years": (0.0, 125.0),
    "body_fat_percent": (1.0, 80.0),
    "volume_m3": (0.002, 0.7),
}
# Any other label of these units: the widest a human measurement can be (a girth, a length).
UNIT_RANGES = {"cm": (0.0, 300.0), "kg": (0.0, 650.0), "kg/m^2": (8.0, 120.0), "years": (0.0, 125.0),
               "%": (0.0, 100.0), "m^3": (0.0, 0.7), "m^2": (0.0, 5.0)}
# Unit-less column names a user is likely to write -> the label name they mean.
LABEL_SUGGESTIONS = {"stature": "stature_cm", "height": "stature_cm", "mass": "mass_kg", "weight": "mass_kg",
                     "bmi": "bmi_kg_m2", "age": "age_years", "body_fat": "body_fat_percent", "volume": "volume_m3",
                     "gender": "gender_1"}
# A unit written another way, or in a unit labels are not read in -> (the suffix we read, the
# unit its values must be converted from, or "" when only the name is wrong).
UNIT_SPELLINGS = {
    "yrs": ("_years", ""), "yr": ("_years", ""), "year": ("_years", ""), "y": ("_years", ""), "a": ("_years", ""),
    "kgs": ("_kg", ""), "kilo": ("_kg", ""), "kilos": ("_kg", ""), "kilograms": ("_kg", ""),
    "kilogram": ("_kg", ""), "cms": ("_cm", ""), "centimeters": ("_cm", ""), "centimetres": ("_cm", ""),
    "centimeter": ("_cm", ""), "centimetre": ("_cm", ""), "pct": ("_percent", ""), "perc": ("_percent", ""),
    "%": ("_percent", ""), "mm": ("_cm", "mm"), "m": ("_cm", "m"), "in": ("_cm", "inches"),
    "inch": ("_cm", "inches"), "inches": ("_cm", "inches"), "ft": ("_cm", "feet"), "g": ("_kg", "g"),
    "lb": ("_kg", "pounds"), "lbs": ("_kg", "pounds"), "pounds": ("_kg", "pounds"),
    "kgm2": ("_kg_m2", ""), "kg/m2": ("_kg_m2", ""), "kg/m^2": ("_kg_m2", ""), "l": ("_m3", "litres"),
}
SEXES = ("female", "male")
SUBJECT_ID_COLUMN = "subject"
SEX_COLUMN = "sex"
SCAN_COLUMNS = ("scan", "subject", "pose")
MESH_COLUMN = "mesh"

VERTICES_FILE = "vertices.npy"
FACES_FILE = "faces.npy"
SUBJECTS_FILE = "subjects.csv"
SCANS_FILE = "scans.csv"
ROTATIONS_FILE = "rotations.npy"
META_FILE = "meta.json"
# Optional: the landmark file of the database's topology (a ``measure.load_landmarks`` document,
# written by ``bodyspace import --landmarks``); ``BodyModel.fit`` keeps the measurement set it gives.
LANDMARKS_FILE = "landmarks.json"
# Kind in the .bodyspace marker of a database folder (bodyspace.atomic): --force replaces only these.
DATABASE_KIND = "database"

# Scans checked for NaN per step while loading: bounds the memory the check touches at once
# (256 scans of 13k vertices are 40 MB) while the result stays a lazy memmap.
_CHECK_CHUNK = 256
# Mesh files from_meshes reads: meshes with faces (an STL file's triangle corners are welded into
# shared vertices), and NPY files of (V, 3) vertices whose faces come from another file.
MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".stl", ".npy")

Table = dict[str, np.ndarray]


# ----------------------------------------------------------------------------------------------
# Label columns and CSV tables
# ----------------------------------------------------------------------------------------------

def unit_of_label(column: str) -> str | None:
    """The unit a label column's suffix declares (``'waist_cm'`` -> ``'cm'``), or None."""
    for suffix in sorted(LABEL_UNITS, key=len, reverse=True):
        if column.endswith(suffix) and len(column) > len(suffix):
            return LABEL_UNITS[suffix]
    return None


def check_label_columns(columns, reserved: tuple[str, ...], source: str) -> None:
    """Raise DatabaseError for a column that is neither reserved nor ends in a known unit suffix."""
    for column in columns:
        if column not in reserved and unit_of_label(column) is None:
            raise DatabaseError(
                f"{source}: unknown column '{column}'{_suggestion(column)}. Expected one of {', '.join(reserved)} "
                f"or a numeric label whose name ends in its unit: {', '.join(LABEL_UNITS)} (e.g. 'stature_cm', "
                f"'mass_kg', 'bmi_kg_m2', 'gender_1')")


def _suggestion(column: str) -> str:
    """' (did you mean stature_cm?)' for a name we can guess, else ''.

    A unit-less name (``stature``), or a name whose unit is misspelt or not one we read
    (``age_yrs``, ``mass_kgs``, ``stature (cm)``, ``stature_mm``: then the values must be converted
    too, which the suggestion says).
    """
    key = column.strip().lower()
    for ch in "()[]":
        key = key.replace(ch, "_" if ch in "([" else "")
    key = "_".join(part for part in key.replace(" ", "_").replace("-", "_").split("_") if part)
    if key in LABEL_SUGGESTIONS:
        return f" (did you mean {LABEL_SUGGESTIONS[key]}?)"
    if key != column and unit_of_label(key) is not None:         # 'Stature (cm)' -> stature_cm
        return f" (did you mean {key}?)"
    base, _, unit = key.rpartition("_")
    if base and unit in UNIT_SPELLINGS:
        suffix, convert_from = UNIT_SPELLINGS[unit]
        name = LABEL_SUGGESTIONS.get(base, "")
        name = name if name.endswith(suffix) else base + suffix
        if name == column:
            return ""
        if convert_from:
            return (f" (did you mean {name}? its values are read in {LABEL_UNITS[suffix]}: "
                    f"convert them from {convert_from} and rename the column)")
        return f" (did you mean {name}?)"
    if any(word in key for word in ("girth", "circumference", "length", "width", "depth", "size")):
        return f" (did you mean {key}_cm?)"
    return ""


def check_label_ranges(table: Mapping[str, np.ndarray], source: str, lines: list[int] | None = None) -> None:
    """Refuse a label value implausible for a human (PLAUSIBLE_LABELS, else UNIT_RANGES by unit).

    table: {column: (n,) values}; non-numeric and NaN (missing) values are skipped.
    """
    for column, values in table.items():
        values = np.asarray(values)
        unit = unit_of_label(column)
        if values.dtype.kind != "f" or unit is None:
            continue
        bounds = PLAUSIBLE_LABELS.get(column, UNIT_RANGES.get(unit))
        if bounds is None:
            continue
        low, high = bounds
        outside = ~np.isnan(values) & ((values < low) | (values > high))
        if outside.any():
            i = int(np.argmax(outside))
            raise DatabaseError(f"{_position(source, lines, i)}, column '{column}': {values[i]:g} {unit} is not "
                                f"plausible for a human; expected {low:g} to {high:g} {unit} (is it in another unit?)")


def _position(source: str, lines: list[int] | None, i: int) -> str:
    """Where value i came from: its line in a file, else its row in an in-memory column."""
    return f"{source}, line {lines[i]}" if lines is not None else f"{source}, row {i}"


def label_values(column: str, values, source: str, lines: list[int] | None = None) -> np.ndarray:
    """One subject column -> (n,) str array (``subject``, ``sex``) or float64 (unit-suffixed labels).

    ``values`` are CSV cells (str) or numbers; an empty cell is a missing label (NaN).
    ``lines`` (file line of each value) make the messages point into the file.
    """
    values = np.asarray(values)
    if values.ndim != 1:
        raise DatabaseError(f"{source}: column '{column}' has shape {values.shape}, expected (n_subjects,)")
    if column == SEX_COLUMN:
        sexes = np.char.lower(np.char.strip(values.astype(str)))
        for i, sex in enumerate(sexes.tolist()):
            if sex not in SEXES:
                empty = " (empty: give it on at least one of the subject's rows, or leave the column out)" if not sex else ""
                raise DatabaseError(f"{_position(source, lines, i)}, column '{column}': '{sex}', "
                                    f"expected one of {', '.join(SEXES)}{empty}")
        return sexes
    if unit_of_label(column) is None:
        return values.astype(str)
    if values.dtype.kind in "biuf":
        numbers = values.astype(np.float64)
    else:
        numbers = np.empty(len(values), dtype=np.float64)
        for i, cell in enumerate(values.astype(str).tolist()):
            try:
                numbers[i] = float(cell) if cell.strip() else math.nan
            except ValueError:
                raise DatabaseError(f"{_position(source, lines, i)}, column '{column}': '{cell}' is not a number "
                                    f"(expected a number in {unit_of_label(column)}, or empty if unknown)") from None
    infinite = np.isinf(numbers)
    if infinite.any():
        i = int(np.argmax(infinite))
        raise DatabaseError(f"{_position(source, lines, i)}, column '{column}': infinite, expected a finite number")
    return numbers


def subject_table(columns: Mapping, source: str, lines: list[int] | None = None) -> Table:
    """{column: (n_subjects,) values} -> typed table; checks columns, ids and duplicates."""
    check_label_columns(list(columns), (SUBJECT_ID_COLUMN, SEX_COLUMN), source)
    if SUBJECT_ID_COLUMN not in columns:
        raise DatabaseError(f"{source}: no '{SUBJECT_ID_COLUMN}' column, found {list(columns)}")
    table = {name: label_values(name, values, source, lines) for name, values in columns.items()}
    lengths = {name: len(values) for name, values in table.items()}
    if len(set(lengths.values())) > 1:
        raise DatabaseError(f"{source}: columns have different lengths {lengths}, expected one value per subject")
    first: dict[str, int] = {}
    for i, subject_id in enumerate(table[SUBJECT_ID_COLUMN].tolist()):
        if not subject_id.strip():
            raise DatabaseError(f"{_position(source, lines, i)}: empty subject id, expected a non-empty string")
        if subject_id in first:
            earlier = f"line {lines[first[subject_id]]}" if lines is not None else f"row {first[subject_id]}"
            raise DatabaseError(f"{_position(source, lines, i)}: subject '{subject_id}' already listed on {earlier}, "
                                f"expected one row per subject")
        first[subject_id] = i
    return table


def scan_table(columns: Mapping, n_scans: int, source: str, lines: list[int] | None = None) -> Table:
    """{'scan' (optional, default 0..n-1), 'subject', 'pose'} -> {'scan': int64, 'subject': str, 'pose': str}."""
    unknown = [name for name in columns if name not in SCAN_COLUMNS]
    missing = [name for name in ("subject", "pose") if name not in columns]
    if unknown or missing:
        raise DatabaseError(f"{source}: columns {list(columns)}; expected {', '.join(SCAN_COLUMNS)}"
                            + (f" (unknown column {', '.join(map(repr, unknown))})" if unknown else "")
                            + (f" (missing {', '.join(map(repr, missing))})" if missing else ""))
    scan = np.asarray(columns["scan"]) if "scan" in columns else np.arange(n_scans)
    if scan.dtype.kind not in "iu":
        cells, scan = scan.astype(str).tolist(), np.empty(len(scan), dtype=np.int64)
        for i, cell in enumerate(cells):
            try:
                scan[i] = int(cell)
            except ValueError:
                raise DatabaseError(f"{_position(source, lines, i)}, column 'scan': '{cell}' is not an "
                                    f"integer index") from None
    table = {"scan": scan.astype(np.int64)}
    for name in ("subject", "pose"):
        table[name] = np.asarray(columns[name]).astype(str)
        empty = np.char.strip(table[name]) == ""
        if empty.any():
            raise DatabaseError(f"{_position(source, lines, int(np.argmax(empty)))}, column '{name}': empty, "
                                f"expected a name")
    return table


# A number written with a decimal comma (a semicolon- or tab-separated spreadsheet export).
_DECIMAL_COMMA = re.compile(r"[-+]?\d+,\d+")


def read_csv_columns(path: Path) -> tuple[dict[str, list[str]], list[int]]:
    """A CSV file -> ({column: stripped cells}, file line of each row). Blank lines are skipped.

    Commas separate the fields; a header with none but semicolons or tabs is a spreadsheet's
    export in a locale that writes decimal commas (``mesh;stature_cm`` / ``a.obj;171,5``): read
    with that separator, a cell that is a number with a decimal comma as that number.
    """
    if not path.is_file():
        raise DatabaseError(f"{path}: file not found")
    try:
        with open(path, newline="", encoding="utf-8-sig") as handle:
            first = handle.readline()
            handle.seek(0)
            delimiter = next((d for d in (";", "\t") if "," not in first and d in first), ",")
            reader = csv.reader(handle, delimiter=delimiter)
            header = [name.strip() for name in next(reader, [])]
            rows, lines = [], []
            for row in reader:
                if not any(cell.strip() for cell in row):
                    continue  # e.g. a trailing empty line from a spreadsheet
                if len(row) != len(header):
                    raise DatabaseError(f"{path}, line {reader.line_num}: {len(row)} fields, "
                                        f"expected {len(header)} (one per header column)")
                cells = [cell.strip() for cell in row]
                if delimiter != ",":
                    cells = [c.replace(",", ".") if _DECIMAL_COMMA.fullmatch(c) else c for c in cells]
                rows.append(cells)
                lines.append(reader.line_num)
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise DatabaseError(f"{path}: could not read as CSV: {exc}") from exc
    if not header or header == [""]:
        raise DatabaseError(f"{path}: empty file, expected a header row")
    if len(set(header)) != len(header):
        duplicate = next(name for name in header if header.count(name) > 1)
        raise DatabaseError(f"{path}: column '{duplicate}' appears twice, expected unique column names")
    return {name: [row[i] for row in rows] for i, name in enumerate(header)}, lines


def write_csv_table(path: Path, table: Mapping[str, np.ndarray]) -> None:
    """Write {column: (n,) array} as CSV, atomically; floats round-trip exactly, NaN as empty."""
    columns = list(table)
    formatted = []
    for name in columns:
        values = np.asarray(table[name])
        if values.dtype.kind == "f":
            formatted.append(["" if math.isnan(x) else repr(float(x)) for x in values.tolist()])
        else:
            formatted.append([str(x) for x in values.tolist()])
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="", encoding="utf-8") as handle:
            writer = csv.writer(handle)
            writer.writerow(columns)
            writer.writerows(zip(*formatted))


# ----------------------------------------------------------------------------------------------
# Consistency checks shared by load, the constructor and the writer
# ----------------------------------------------------------------------------------------------

def check_vertices(vertices: np.ndarray, source: str) -> None:
    """``vertices`` must be (N, V, 3) floats and finite; checked in chunks so a memmap is never read whole."""
    if vertices.ndim != 3 or vertices.shape[2] != 3:
        raise DatabaseError(f"{source}: shape {vertices.shape}, expected (n_scans, n_vertices, 3)")
    if vertices.dtype.kind != "f":
        raise DatabaseError(f"{source}: dtype {vertices.dtype}, expected floating point coordinates")
    for start, block in iter_blocks(vertices, _CHECK_CHUNK):
        finite = np.isfinite(block).all(axis=(1, 2))
        if not finite.all():
            raise DatabaseError(f"{source}: scan {start + int(np.argmin(finite))} contains NaN or infinity, "
                                f"expected finite coordinates")


def check_faces(faces: np.ndarray, n_vertices: int, source: str) -> None:
    """``faces`` must be (F, 3) integers in [0, n_vertices)."""
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise DatabaseError(f"{source}: shape {faces.shape}, expected (n_faces > 0, 3)")
    if faces.dtype.kind not in "iu":
        raise DatabaseError(f"{source}: dtype {faces.dtype}, expected integers")
    if faces.min() < 0 or faces.max() >= n_vertices:
        raise DatabaseError(f"{source}: faces index vertices {faces.min()}..{faces.max()}, "
                            f"expected 0..{n_vertices - 1} (the meshes have {n_vertices} vertices)")


def check_tables(subjects: Table, scans: Table, n_scans: int, subjects_source: str, scans_source: str,
                 vertices_source: str = "vertices") -> None:
    """Scans and subjects agree: one scan row per mesh, numbered 0..n-1, every subject known."""
    if len(scans["scan"]) != n_scans:
        raise DatabaseError(f"{scans_source}: {len(scans['scan'])} scan rows, but {vertices_source} holds "
                            f"{n_scans} scans; expected one row per scan")
    if not np.array_equal(scans["scan"], np.arange(n_scans)):
        bad = int(np.argmax(scans["scan"] != np.arange(n_scans)))
        raise DatabaseError(f"{scans_source}: row {bad} has scan {scans['scan'][bad]}, expected the rows to "
                            f"number the meshes 0..{n_scans - 1} in order")
    known = set(subjects[SUBJECT_ID_COLUMN].tolist())
    unknown = sorted(set(scans["subject"].tolist()) - known)
    if unknown:
        raise DatabaseError(f"{scans_source}: subject(s) {', '.join(map(repr, unknown[:5]))}"
                            f"{' ...' if len(unknown) > 5 else ''} not found in {subjects_source}")


def check_rotations(rotations: np.ndarray | None, joints, n_scans: int, source: str) -> None:
    """``rotations`` (n_scans, J, 3) float with J == len(joints); both present or both absent."""
    if rotations is None:
        if joints is not None:
            raise DatabaseError(f"{source}: joint names given but no rotations, expected both or neither")
        return
    if rotations.ndim != 3 or rotations.shape[0] != n_scans or rotations.shape[2] != 3:
        raise DatabaseError(f"{source}: shape {rotations.shape}, expected ({n_scans}, n_joints, 3)")
    if rotations.dtype.kind != "f":
        raise DatabaseError(f"{source}: dtype {rotations.dtype}, expected float32 axis-angle rotations")
    if joints is None or len(joints) != rotations.shape[1]:
        found = "none" if joints is None else len(joints)
        raise DatabaseError(f"{source}: {rotations.shape[1]} joints per scan, but {found} joint names "
                            f"(meta.json 'joints'); expected one name per joint")
    if not all(np.isfinite(block).all() for _, block in iter_blocks(rotations, 16 * _CHECK_CHUNK)):
        raise DatabaseError(f"{source}: contains NaN or infinity, expected finite rotations")


def iter_blocks(array: np.ndarray, size: int) -> Iterator[tuple[int, np.ndarray]]:
    """``(start, array[start:start + size])`` over the first axis. A memory map of a whole .npy
    file is read from the file (``rowfile.read_rows``), so a pass over it does not leave the
    file mapped into the process (its resident size would grow to the file's)."""
    path = getattr(array, "filename", None) if isinstance(array, np.memmap) else None
    layout = None
    if path is not None:
        try:
            layout = npy_layout(path)
        except (OSError, ValueError, DatabaseError):
            layout = None
        if layout is not None and (layout[0] != array.shape or layout[1] != array.dtype):
            layout = None  # a view of part of the file: read through the map
    for start in range(0, len(array), size):
        yield start, (read_rows(path, start, start + size, layout) if layout is not None
                      else np.asarray(array[start:start + size]))


def write_database_tables(folder: Path, faces: np.ndarray, subjects: Mapping, scans: Mapping,
                          meta: Mapping, joints: list[str] | None = None) -> None:
    """Complete a database folder whose ``vertices.npy`` (and ``rotations.npy`` with ``joints``)
    were written in chunks (``rowfile.write_rows``): check everything together as
    ``write_database`` does, then write faces, the two tables and meta.json beside them."""
    folder = Path(folder)
    vertices = np.load(folder / VERTICES_FILE, mmap_mode="r", allow_pickle=False)
    rotations = (np.load(folder / ROTATIONS_FILE, mmap_mode="r", allow_pickle=False)
                 if (folder / ROTATIONS_FILE).is_file() else None)
    vertices, faces, subjects, scans, meta, rotations = validate_database(
        vertices, faces, subjects, scans, meta, rotations, joints)
    np.save(folder / FACES_FILE, faces.astype(np.int32), allow_pickle=False)
    write_csv_table(folder / SUBJECTS_FILE, subjects)
    write_csv_table(folder / SCANS_FILE, scans)
    (folder / META_FILE).write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")


# ----------------------------------------------------------------------------------------------
# Writer
# ----------------------------------------------------------------------------------------------

def validate_database(vertices, faces, subjects: Mapping, scans: Mapping, meta: Mapping | None,
                      rotations: np.ndarray | None, joints: list[str] | None = None):
    """Check in-memory database parts together; return them normalized.

    Returns (vertices, faces, subject table, scan table, meta with counts, rotations). A memmap
    ``vertices`` stays a view of its file.
    """
    if not isinstance(vertices, np.ndarray):  # a memmap stays one: check_vertices reads it by pread
        vertices = np.asarray(vertices)
    faces = np.asarray(faces)
    check_vertices(vertices, "vertices")
    check_faces(faces, vertices.shape[1], "faces")
    subjects = subject_table(subjects, "subjects")
    scans = scan_table(scans, len(vertices), "scans")
    check_tables(subjects, scans, len(vertices), "subjects", "scans")
    rotations = None if rotations is None else np.asarray(rotations)
    meta = dict(meta or {})
    joints = list(joints) if joints is not None else meta.get("joints")
    check_rotations(rotations, joints, len(vertices), "rotations")
    meta = build_meta(meta, vertices.shape, len(faces), joints)
    return vertices, faces, subjects, scans, meta, rotations


def write_database(folder: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray, subjects: Mapping,
                   scans: Mapping, meta: Mapping | None = None, rotations: np.ndarray | None = None,
                   joints: list[str] | None = None, overwrite: bool = False,
                   extra_files: Mapping[str, str] | None = None) -> Path:
    """Write a database folder; it appears complete or not at all (temp folder, then rename).

    vertices (N, V, 3) in metres (any float; stored float32, copied in chunks so a memmap
    input is never loaded whole); faces (F, 3) int; subjects {column: (n_subjects,)};
    scans {'subject', 'pose', optional 'scan': (N,)}; meta: template, provenance, licence,
    units (counts and format_version are filled in here); rotations (N, J, 3) axis-angle with
    ``joints`` (J names); extra_files: file name -> text written into the folder too (e.g.
    ``LANDMARKS_FILE``). Returns the folder path.
    """
    folder = Path(folder)
    if folder.exists():
        if not overwrite:
            raise DatabaseError(f"{folder}: already exists; pass overwrite=True to replace it")
        check_replaceable_folder(folder, DATABASE_KIND)  # refused before the work, not after
    vertices, faces, subjects, scans, meta, rotations = validate_database(
        vertices, faces, subjects, scans, meta, rotations, joints)
    if meta["units"].get("length") != "m":
        raise DatabaseError(f"meta: units {meta['units']!r}, expected length in 'm' (convert the vertices to metres)")
    try:
        meta_text = json.dumps(meta, indent=2) + "\n"
    except (TypeError, ValueError) as exc:
        raise DatabaseError(f"meta: cannot be written as JSON ({exc}); expected plain str/number/list/dict values") from exc
    with atomic_dir(folder, overwrite=overwrite, kind=DATABASE_KIND) as tmp:
        if len(vertices) == 0:
            np.save(tmp / VERTICES_FILE, np.zeros(vertices.shape, dtype=np.float32), allow_pickle=False)
        else:
            # Chunked copy with file reads and writes (rowfile), not through maps: neither a memmap
            # input (a loaded database) nor the output is ever held in memory whole.
            create_rows(tmp / VERTICES_FILE, vertices.shape, np.float32)
            for start, block in iter_blocks(vertices, _CHECK_CHUNK):
                write_rows(tmp / VERTICES_FILE, start, block)
        np.save(tmp / FACES_FILE, faces.astype(np.int32), allow_pickle=False)
        if rotations is not None:
            np.save(tmp / ROTATIONS_FILE, rotations.astype(np.float32), allow_pickle=False)
        write_csv_table(tmp / SUBJECTS_FILE, subjects)
        write_csv_table(tmp / SCANS_FILE, scans)
        (tmp / META_FILE).write_text(meta_text, encoding="utf-8")
        for name, text in (extra_files or {}).items():
            (tmp / name).write_text(text, encoding="utf-8")
    return folder


def build_meta(meta: Mapping, vertices_shape: tuple, n_faces: int, joints) -> dict:
    """meta.json content: the caller's fields, defaults for missing ones, counts from the arrays."""
    result = {
        "format_version": FORMAT_VERSION,
        "template": str(meta.get("template", "custom")),
        "units": dict(meta.get("units", {"length": "m"})),
        "provenance": dict(meta.get("provenance", {})),
        "licence": str(meta.get("licence", "unspecified")),
        "n_scans": int(vertices_shape[0]),
        "n_vertices": int(vertices_shape[1]),
        "n_faces": int(n_faces),
    }
    # Fields we do not know about are kept, not dropped.
    result.update({key: value for key, value in meta.items() if key not in result and key != "joints"})
    if joints is not None:
        result["joints"] = [str(j) for j in joints]
    return result


# ----------------------------------------------------------------------------------------------
# Reader
# ----------------------------------------------------------------------------------------------

def as_path(value, what: str) -> Path:
    """``value`` (str or os.PathLike) as a Path; DatabaseError naming ``what`` for None, numbers, bytes, ''."""
    if isinstance(value, Path):
        return value
    if not isinstance(value, (str, os.PathLike)) or isinstance(os.fspath(value), bytes):
        raise DatabaseError(f"{what} {value!r} is a {type(value).__name__}, expected a path (str or pathlib.Path)")
    if not os.fspath(value):
        raise DatabaseError(f"{what} is an empty string, expected a path")
    return Path(value)


def read_meta(path: Path) -> dict:
    """meta.json -> dict, with format_version and required fields checked."""
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatabaseError(f"{path}: could not read as JSON: {exc}") from exc
    if not isinstance(meta, dict):
        raise DatabaseError(f"{path}: top level is {type(meta).__name__}, expected a JSON object")
    version = meta.get("format_version")
    if version != FORMAT_VERSION:
        raise DatabaseError(f"{path}: format_version {version!r}, expected {FORMAT_VERSION} "
                            f"(written by another bodyspace version?)")
    required = ("template", "units", "provenance", "licence", "n_scans", "n_vertices", "n_faces")
    missing = [key for key in required if key not in meta]
    if missing:
        raise DatabaseError(f"{path}: missing field(s) {', '.join(missing)}, expected {', '.join(required)}")
    if not isinstance(meta["units"], dict) or meta["units"].get("length") != "m":
        raise DatabaseError(f"{path}: units {meta['units']!r}, expected {{\"length\": \"m\", ...}}")
    joints = meta.get("joints")
    if joints is not None and (not isinstance(joints, list) or not all(isinstance(j, str) for j in joints)):
        raise DatabaseError(f"{path}: joints {joints!r}, expected a list of joint names (str)")
    return meta


_NPY_MAGIC = b"\x93NUMPY"


def _load_npy(path: Path, mmap: bool) -> np.ndarray:
    """A numeric .npy array, never unpickled: numpy calls any non-NPY file 'pickled data' (and
    suggests loading it unsafely), so the magic string is checked first."""
    try:
        with open(path, "rb") as handle:
            head = handle.read(len(_NPY_MAGIC))
    except OSError as exc:
        raise DatabaseError(f"{path}: could not read: {exc.strerror or exc}") from exc
    if head != _NPY_MAGIC:
        raise DatabaseError(f"{path}: not a .npy file (it starts with {head!r}); expected a numeric array written "
                            "by numpy.save")
    try:
        return np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except ValueError as exc:
        if "allow_pickle" in str(exc) or "pickled" in str(exc):
            raise DatabaseError(f"{path}: holds Python objects, which bodyspace never loads (no pickle); expected "
                                "a numeric array written by numpy.save") from None
        raise DatabaseError(f"{path}: could not read as a numeric .npy array: {exc}") from exc
    except (OSError, EOFError) as exc:
        raise DatabaseError(f"{path}: could not read as a numeric .npy array ({exc}); it may be truncated") from exc


def load_database_arrays(folder: Path, check_values: bool = True) -> dict:
    """Read and validate every file of a database folder; the parts of a ScanDatabase."""
    if not folder.is_dir():
        raise DatabaseError(f"{folder}: not a folder, expected a scan database folder")
    missing = [name for name in (META_FILE, VERTICES_FILE, FACES_FILE, SUBJECTS_FILE, SCANS_FILE)
               if not (folder / name).is_file()]
    if missing:
        raise DatabaseError(f"{folder}: missing {', '.join(missing)}; a scan database folder holds "
                            f"{META_FILE}, {VERTICES_FILE}, {FACES_FILE}, {SUBJECTS_FILE}, {SCANS_FILE}")
    meta = read_meta(folder / META_FILE)
    vertices = _load_npy(folder / VERTICES_FILE, mmap=True)
    if vertices.ndim != 3 or vertices.shape[2] != 3 or vertices.dtype != np.float32:
        raise DatabaseError(f"{folder / VERTICES_FILE}: shape {vertices.shape} dtype {vertices.dtype}, "
                            f"expected (n_scans, n_vertices, 3) float32")
    if check_values:
        check_vertices(vertices, str(folder / VERTICES_FILE))
    faces = _load_npy(folder / FACES_FILE, mmap=False)
    check_faces(faces, vertices.shape[1], str(folder / FACES_FILE))
    subject_columns, subject_lines = read_csv_columns(folder / SUBJECTS_FILE)
    subjects = subject_table(subject_columns, str(folder / SUBJECTS_FILE), subject_lines)
    scan_columns, scan_lines = read_csv_columns(folder / SCANS_FILE)
    scans = scan_table(scan_columns, len(vertices), str(folder / SCANS_FILE), scan_lines)
    check_tables(subjects, scans, len(vertices), str(folder / SUBJECTS_FILE), str(folder / SCANS_FILE),
                 str(folder / VERTICES_FILE))
    rotations = None
    if (folder / ROTATIONS_FILE).is_file():
        rotations = _load_npy(folder / ROTATIONS_FILE, mmap=True)
    check_rotations(rotations, meta.get("joints"), len(vertices), str(folder / ROTATIONS_FILE))
    counts = {"n_scans": vertices.shape[0], "n_vertices": vertices.shape[1], "n_faces": faces.shape[0]}
    for key, found in counts.items():
        if meta[key] != found:
            raise DatabaseError(f"{folder / META_FILE}: {key} is {meta[key]}, but the arrays hold {found}")
    return {"vertices": vertices, "faces": faces.astype(np.int64), "subjects": subjects, "scans": scans,
            "meta": meta, "rotations": rotations}


# ----------------------------------------------------------------------------------------------
# A user's own registered meshes
# ----------------------------------------------------------------------------------------------

_LENGTH_UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}
# A folder whose Y extent is below this share of its tallest extent (median over the meshes) does
# not stand along Y. A T-pose is about as wide as tall, so only a clearly shorter Y counts.
UP_EXTENT_SHARE = 0.6
# Feet end vs head end: bounding-box area (across the up axis) of the lowest vs the highest 5 %
# of a body's height. Over the 39 library poses the median is 3.6 (0.7 bending forward, 16 with
# the arms overhead); a folder whose median is below 1 / UPSIDE_DOWN_RATIO stands on its head.
END_SLAB = 0.05
UPSIDE_DOWN_RATIO = 1.5
MIXED_TOPOLOGY = ("expected every mesh registered to one topology (mixed topology); register this one to the "
                  "others' topology, or leave it out of the CSV")
# Per-scan values of one subject's label may differ (weighed on two days, measured per scan) by
# this share of their median; more is more likely two people under one id or a typo.
LABEL_SPREAD = 0.10
# How each option of read_mesh_folder is written in a message: the API's keyword, or the flag of
# `bodyspace import` (``spelling="cli"``), so a refusal says the fix in the user's words.
_OPTION_SPELLING = {
    "api": {"length_unit": "length_unit='{}'", "up": "up='{}'", "faces": "faces={}", "rest_pose": "rest_pose='{}'"},
    "cli": {"length_unit": "--units {}", "up": "--up {}", "faces": "--faces {}", "rest_pose": "--rest-pose {}"},
}


def _say(spelling: str, option: str, value) -> str:
    """How the user sets ``option`` to ``value`` in their interface: ``--units mm`` or ``length_unit='mm'``."""
    return _OPTION_SPELLING.get(spelling, _OPTION_SPELLING["api"])[option].format(value)


def read_mesh_folder(folder: Path, labels_csv: Path, length_unit: str = "m", up: str | None = None,
                     faces: str | os.PathLike | None = None, rest_pose: str | None = None,
                     spelling: str = "api") -> dict:
    """Registered meshes + labels CSV -> the parts of a ScanDatabase (vertices in memory, float32,
    metres, +Y up).

    labels_csv: required ``mesh`` (file name relative to ``folder``: OBJ, PLY, GLB/GLTF, STL, or
    NPY holding (V, 3) vertices), optional ``subject`` (default: the mesh file stem) and ``pose``
    (default 'rest'), plus label columns with unit suffixes. A label is one value per subject:
    where a subject's scans give different values, the rest-pose scan's value is kept (the scan
    the semantic regressors learn from), else the mean of the given ones, and a note says so
    (``meta['import_notes']``); values more than ``LABEL_SPREAD`` apart are refused.

    length_unit: 'm', 'cm' or 'mm', the unit of the mesh coordinates. up: the meshes' up axis
    ('y', '-y', 'z', '-z', 'x', '-x'), turned to +Y; None: +Y, checked (a folder that is tallest
    along another axis, or stands on its head, is refused with the ``up`` to pass). faces: the
    faces of NPY meshes, a mesh file of the same topology or an (F, 3) integer .npy; default: the
    first mesh of the CSV that has faces. rest_pose: the rest pose's name or 'first' (used to
    reduce per-scan labels; ``choose_rest_pose`` checks it). spelling: 'api' or 'cli', how
    messages name the options.
    """
    if not isinstance(length_unit, str) or length_unit not in _LENGTH_UNITS:
        raise DatabaseError(f"length unit {length_unit!r}: expected one of {', '.join(_LENGTH_UNITS)} "
                            f"(e.g. {_say(spelling, 'length_unit', 'mm')})")
    if up is not None and (not isinstance(up, str) or up not in UP_ROTATIONS):
        raise DatabaseError(f"up axis {up!r}: expected one of {', '.join(UP_ROTATIONS)} (the axis the meshes' "
                            f"head points along, e.g. {_say(spelling, 'up', 'z')})")
    if not folder.is_dir():
        raise DatabaseError(f"{folder}: not a folder, expected a folder of registered meshes")
    source = str(labels_csv)
    cells, lines = read_csv_columns(labels_csv)
    check_label_columns(cells, (MESH_COLUMN, SUBJECT_ID_COLUMN, "pose", SEX_COLUMN), source)
    if MESH_COLUMN not in cells:
        raise DatabaseError(f"{source}: no '{MESH_COLUMN}' column (mesh file name relative to {folder}), "
                            f"found {list(cells)}")
    if not lines:
        raise DatabaseError(f"{source}: no rows, expected one row per mesh")
    mesh_names = cells[MESH_COLUMN]
    seen: dict[str, int] = {}
    for name, line in zip(mesh_names, lines):
        if name in seen:
            raise DatabaseError(f"{source}, line {line}: mesh '{name}' already listed on line {seen[name]}")
        seen[name] = line
    n_scans = len(lines)
    subject_ids = [sid or Path(name).stem for sid, name in zip(cells.get(SUBJECT_ID_COLUMN, [""] * n_scans), mesh_names)]
    poses = [pose or REST_POSE for pose in cells.get("pose", [""] * n_scans)]
    scans = {"scan": np.arange(n_scans, dtype=np.int64), "subject": np.array(subject_ids, dtype=str),
             "pose": np.array(poses, dtype=str)}
    rule = {"pose": REST_POSE} if rest_pose is None else choose_rest_pose(scans, rest_pose, source)
    # Labels before meshes: a wrong label is said before minutes of reading.
    subjects, notes = _subject_labels(cells, lines, subject_ids, rest_pose_rows(scans, {REST_POSE_FIELD: rule}),
                                      source)

    vertices, faces = _read_registered_meshes(folder, mesh_names, lines, source, faces, spelling)
    if length_unit != "m":
        vertices *= _LENGTH_UNITS[length_unit]
    if up not in (None, "y"):
        rotation = UP_ROTATIONS[up].astype(np.float32)
        for start in range(0, len(vertices), _CHECK_CHUNK):
            vertices[start:start + _CHECK_CHUNK] = vertices[start:start + _CHECK_CHUNK] @ rotation.T
    _check_body_frame(vertices, folder, length_unit, spelling, check_up=up is None)
    meta = build_meta({"template": "custom", "units": {"length": "m"},
                       "provenance": {"source": "from_meshes", "folder": str(folder), "labels": str(labels_csv),
                                      "length_unit": length_unit, "up": up or "y"},
                       **({"import_notes": notes} if notes else {})},
                      vertices.shape, len(faces), None)
    return {"vertices": vertices, "faces": faces, "subjects": subjects, "scans": scans, "meta": meta,
            "rotations": None}


def _subject_labels(cells: Mapping[str, list[str]], lines: list[int], subject_ids: list[str], rest_rows: np.ndarray,
                    source: str) -> tuple[Table, list[str]]:
    """Per-scan CSV cells -> one row per subject (in order of first appearance) and notes.

    Text columns (sex) must agree within a subject (a sex given on some of its scans only is the
    subject's). A numeric label's value of a subject is its
    rest-pose scan's (``rest_rows``, when given there), else the mean of its given values; values
    more than ``LABEL_SPREAD`` of their median apart are refused as two people or a typo.
    """
    first_row: dict[str, int] = {}
    for row, sid in enumerate(subject_ids):
        first_row.setdefault(sid, row)
    members: dict[str, list[int]] = {sid: [] for sid in first_row}
    for row, sid in enumerate(subject_ids):
        members[sid].append(row)
    rest_of: dict[str, int] = {}
    for row in rest_rows:
        rest_of.setdefault(subject_ids[row], int(row))  # a subject's first rest-pose scan
    subjects: Table = {SUBJECT_ID_COLUMN: np.array(list(first_row), dtype=str)}
    notes = []
    for column in cells:
        if column in (MESH_COLUMN, SUBJECT_ID_COLUMN, "pose"):
            continue
        column_cells = list(cells[column])
        if column == SEX_COLUMN:
            # Written on some scans only (the rest-pose row, as a clinic fills it in): the
            # subject's other scans take it; agreement is checked below as for any text.
            for rows in members.values():
                given = next((column_cells[r] for r in rows if str(column_cells[r]).strip()), None)
                for r in rows:
                    if given is not None and not str(column_cells[r]).strip():
                        column_cells[r] = given
        per_scan = label_values(column, column_cells, source, lines)
        check_label_ranges({column: per_scan}, source, lines)
        if per_scan.dtype.kind != "f":
            for sid, rows in members.items():
                other = next((r for r in rows if per_scan[r] != per_scan[rows[0]]), None)
                if other is not None:
                    raise DatabaseError(f"{source}, line {lines[other]}, column '{column}': subject '{sid}' has "
                                        f"'{column_cells[other]}' here but '{column_cells[rows[0]]}' on line "
                                        f"{lines[rows[0]]}; expected one value per subject")
            subjects[column] = per_scan[[rows[0] for rows in members.values()]]
            continue
        values, differing = np.full(len(members), np.nan), []
        for i, (sid, rows) in enumerate(members.items()):
            given = [r for r in rows if not np.isnan(per_scan[r])]
            if not given:
                continue
            v = per_scan[given]
            if v.max() - v.min() > LABEL_SPREAD * abs(float(np.median(v))):
                lo, hi = given[int(np.argmin(v))], given[int(np.argmax(v))]
                raise DatabaseError(f"{source}, column '{column}': subject '{sid}' has {v.min():g} on line {lines[lo]} "
                                    f"and {v.max():g} on line {lines[hi]}, more than {LABEL_SPREAD:.0%} apart; expected "
                                    "one person's value (is the 'subject' column right? is one a typo?)")
            rest = rest_of.get(sid)
            values[i] = per_scan[rest] if rest is not None and rest in given else float(v.mean())
            if v.max() > v.min():
                differing.append(sid)
        if differing:
            notes.append(f"{source}, column '{column}': the scans of {len(differing)} subject(s) "
                         f"({', '.join(map(repr, differing[:3]))}{' ...' if len(differing) > 3 else ''}) give different "
                         "values; each subject's value is its rest-pose scan's, or the mean of its scans' where the "
                         "rest-pose scan has none")
        subjects[column] = values
    return subjects, notes


@dataclass
class _Topology:
    """The faces every mesh of a folder must share, and where they came from.

    faces: (F, 3) int64. n_vertices: V. path: the file they were read from.
    """

    faces: np.ndarray
    n_vertices: int
    path: Path


def _read_registered_meshes(folder: Path, mesh_names: list[str], lines: list[int], source: str,
                            faces_file=None, spelling: str = "api") -> tuple[np.ndarray, np.ndarray]:
    """Meshes sharing one topology -> vertices (N, V, 3) float32, faces (F, 3) int64.

    The topology is ``faces_file``'s, else the first listed mesh that has faces (OBJ, PLY,
    GLB/GLTF, STL); every mesh must have exactly its faces (an STL file: its triangles in the
    same order, see ``_stl_vertices``), every NPY file its vertex count.
    """
    paths = []
    for name, line in zip(mesh_names, lines):
        path = folder / name
        if path.suffix.lower() not in MESH_SUFFIXES:
            raise DatabaseError(f"{source}, line {line}: mesh '{name}' has suffix '{path.suffix}', "
                                f"expected one of {', '.join(MESH_SUFFIXES)}")
        if not path.is_file():
            raise DatabaseError(f"{source}, line {line}: mesh file {path} not found")
        paths.append(path)
    cached: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    if faces_file is not None:
        topology = _faces_from_file(Path(faces_file), spelling)
    else:
        first = next((i for i, p in enumerate(paths) if p.suffix.lower() != ".npy"), None)
        if first is None:
            raise DatabaseError(f"{source}, line {lines[0]}: mesh '{mesh_names[0]}' is a .npy file of vertices "
                                f"only, and no mesh of {source} has faces; expected the faces of the topology: "
                                f"pass {_say(spelling, 'faces', 'FILE')} (a mesh of the same topology, or an (F, 3) "
                                "integer .npy of vertex ids)")
        cached[first] = _load_with_faces(paths[first])
        topology = _Topology(cached[first][1], len(cached[first][0]), paths[first])
    vertices = np.empty((len(paths), topology.n_vertices, 3), dtype=np.float32)
    scales, edges = np.empty(len(paths)), scale_edges(topology.faces)
    for i, path in enumerate(paths):
        suffix = path.suffix.lower()
        if suffix == ".npy":
            mesh_vertices = _npy_vertices(path, topology)
        elif suffix == ".stl":
            mesh_vertices = _stl_vertices(path, topology, cached.pop(i, None))
        else:
            mesh_vertices, mesh_faces = cached.pop(i, None) or load_mesh(path)
            _check_same_topology(path, mesh_vertices, mesh_faces, topology)
        vertices[i] = mesh_vertices
        scales[i] = _mean_edge_length(mesh_vertices, edges)
    _check_common_scale(scales, paths, lines, source)
    return vertices, topology.faces


def _load_with_faces(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A mesh file's vertices (V, 3) and faces (F, 3); an STL file's triangle corners welded into
    shared vertices first (``weld_corners``)."""
    vertices, faces = load_mesh(path)
    if path.suffix.lower() == ".stl":
        vertices, faces = weld_corners(vertices[faces].reshape(-1, 3))
    return vertices, faces


def weld_corners(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangle corners (3F, 3) of an STL file -> shared vertices (V, 3) and faces (F, 3).

    STL stores each triangle's three corners and no vertex list; corners of one vertex repeat its
    coordinates bit for bit. Vertices are numbered in the order the triangles first use them, so
    STL files written from one topology in one triangle order weld to the same faces.
    """
    unique, first, inverse = np.unique(corners, axis=0, return_index=True, return_inverse=True)
    rank = np.empty(len(unique), dtype=np.int64)
    rank[np.argsort(first, kind="stable")] = np.arange(len(unique))
    vertices = np.empty_like(unique)
    vertices[rank] = unique
    return vertices, rank[inverse.reshape(-1)].reshape(-1, 3)


def _faces_from_file(path: Path, spelling: str) -> _Topology:
    """The topology of ``faces``: an (F, 3) integer .npy, or any mesh file."""
    flag = _say(spelling, "faces", path)
    if not path.is_file():
        raise DatabaseError(f"{flag}: file not found; expected a mesh of the meshes' topology or an (F, 3) integer "
                            ".npy of vertex ids")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise DatabaseError(f"{flag}: suffix '{path.suffix}'; expected a mesh of the meshes' topology "
                            f"({', '.join(s for s in MESH_SUFFIXES if s != '.npy')}) or an (F, 3) integer .npy")
    try:
        if path.suffix.lower() != ".npy":
            vertices, faces = _load_with_faces(path)
            return _Topology(faces, len(vertices), path)
        faces = _load_npy(path, mmap=False)
    except BodyspaceError as exc:
        raise DatabaseError(f"{flag}: {str(exc).removeprefix(str(path) + ': ')}") from None
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0 or faces.dtype.kind not in "iu":
        raise DatabaseError(f"{flag}: found an array of shape {faces.shape} and dtype {faces.dtype}; expected "
                            "(F, 3) integer vertex ids, one row per triangle (counted from 0)")
    if faces.min() < 0:
        raise DatabaseError(f"{flag}: found vertex id {faces.min()}; expected ids counted from 0")
    return _Topology(faces.astype(np.int64), int(faces.max()) + 1, path)


def _npy_vertices(path: Path, topology: _Topology) -> np.ndarray:
    """An NPY mesh: (V, 3) finite coordinates, V the topology's vertex count."""
    vertices = _load_npy(path, mmap=False)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or vertices.dtype.kind not in "iuf":
        raise DatabaseError(f"{path}: found an array of shape {vertices.shape} and dtype {vertices.dtype}; expected "
                            "(V, 3) vertex coordinates, one row per vertex (np.save(path, vertices))")
    if len(vertices) != topology.n_vertices:
        # a faces .npy knows only its largest vertex id; a mesh file its vertex count
        which = (f"use vertex ids 0..{topology.n_vertices - 1}" if topology.path.suffix.lower() == ".npy"
                 else f"are for {topology.n_vertices} vertices")
        raise DatabaseError(f"{path}: {len(vertices)} vertices, but the faces of {topology.path} {which}; "
                            f"{MIXED_TOPOLOGY}")
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise DatabaseError(f"{path}: {int(bad.sum())} vertices contain NaN or infinity (first: vertex "
                            f"{int(np.argmax(bad))}), expected finite coordinates")
    return vertices.astype(np.float64)


def _stl_vertices(path: Path, topology: _Topology, loaded=None) -> np.ndarray:
    """An STL mesh on ``topology``: its triangles, in file order, are the topology's faces, so
    corner k of triangle f is vertex ``faces[f, k]``; the corners of one vertex must agree."""
    if loaded is not None:  # the folder's reference itself, welded already
        return loaded[0]
    corners, triangles = load_mesh(path)
    corners = corners[triangles]                                     # (F, 3, 3)
    if len(corners) != len(topology.faces):
        raise DatabaseError(f"{path}: {len(corners)} triangles, but {topology.path} has {len(topology.faces)}; "
                            f"{MIXED_TOPOLOGY}")
    vertices = np.full((topology.n_vertices, 3), np.nan)
    vertices[topology.faces.reshape(-1)] = corners.reshape(-1, 3)
    if np.isnan(vertices).any():
        raise DatabaseError(f"{path}: {topology.path} has {int(np.isnan(vertices[:, 0]).sum())} vertices no triangle "
                            "uses, which an STL file cannot hold; expected a topology of triangles only (remove the "
                            "unused vertices, or use OBJ/PLY files)")
    off = np.abs(vertices[topology.faces] - corners).max(axis=2)     # (F, 3)
    scale = float(np.abs(corners).max()) or 1.0
    if off.max() > 1e-6 * scale:
        f, k = np.unravel_index(int(np.argmax(off)), off.shape)
        raise DatabaseError(f"{path}: corner {k} of triangle {f} is {off[f, k]:.3g} away from the other corners of its "
                            f"vertex {topology.faces[f, k]} (faces of {topology.path}); expected STL files written "
                            "from one registered topology with the triangles in one order")
    return vertices


def _check_same_topology(path: Path, vertices: np.ndarray, faces: np.ndarray, topology: _Topology) -> None:
    """A mesh with faces must have the topology's vertex count and exactly its faces."""
    if len(vertices) != topology.n_vertices:
        raise DatabaseError(f"{path}: {len(vertices)} vertices, but {topology.path} has {topology.n_vertices}; "
                            f"{MIXED_TOPOLOGY}")
    if not np.array_equal(faces, topology.faces):
        detail = (f"{len(faces)} faces vs {len(topology.faces)}" if len(faces) != len(topology.faces) else
                  f"{int((faces != topology.faces).any(axis=1).sum())} of {len(faces)} faces differ")
        raise DatabaseError(f"{path}: faces differ from {topology.path} ({detail}); {MIXED_TOPOLOGY}")


def _check_body_frame(vertices: np.ndarray, folder: Path, length_unit: str, spelling: str,
                      check_up: bool = True) -> None:
    """Refuse a folder that is not human-sized in metres or (``check_up``) does not stand along +Y.

    vertices (N, V, 3), metres by ``length_unit``. The median bounding box over the meshes must
    be human-sized (``BODY_EXTENT_M``: else the unit is wrong, and the one that fits is named);
    Y must not be clearly shorter than the tallest axis (``UP_EXTENT_SHARE``), and the feet end
    must be the wider one (``UPSIDE_DOWN_RATIO``): else the ``up`` that fits is named.
    """
    extents = np.empty((len(vertices), 3))
    for start in range(0, len(vertices), _CHECK_CHUNK):
        chunk = vertices[start:start + _CHECK_CHUNK]
        extents[start:start + _CHECK_CHUNK] = chunk.max(axis=1) - chunk.min(axis=1)
    extent = np.median(extents, axis=0)
    size = float(extent.max())
    lo, hi = BODY_EXTENT_M
    where = (f"{folder}: the meshes are {size:.4g} m across (the largest side of their median bounding box, "
             f"{len(vertices)} meshes read in {length_unit})")
    if not lo <= size <= hi:
        raw = size / _LENGTH_UNITS[length_unit]
        fits = [u for u, f in _LENGTH_UNITS.items() if lo <= raw * f <= hi]
        fix = (f"are they in {fits[0]}? pass {_say(spelling, 'length_unit', fits[0])}" if fits else
               "scale them to metres, centimetres or millimetres")
        raise DatabaseError(f"{where}; expected a human body, {lo:g} to {hi:g} m; {fix}")
    if not check_up:
        return
    axis = 1 if extent[1] >= UP_EXTENT_SHARE * size else int(np.argmax(extent))
    ratios = [_end_ratio(v, axis) for v in vertices[:: max(1, len(vertices) // 64)]]   # at most ~64 meshes
    sign = "-" if np.median(ratios) < 1.0 / UPSIDE_DOWN_RATIO else ""
    if axis == 1 and not sign:
        return
    up = sign + "xyz"[axis]
    found = (f"they stand on their heads along Y (the wider end, the feet, is at +Y)" if axis == 1 else
             f"they are tallest along {'XYZ'[axis]} ({extent[axis]:.3g} m) and {extent[1]:.3g} m along Y")
    raise DatabaseError(f"{where}: {found}; expected +Y up; pass {_say(spelling, 'up', up)} to turn them (or "
                        f"{_say(spelling, 'up', 'y')} if they really stand along +Y)")


def _end_ratio(vertices: np.ndarray, axis: int) -> float:
    """Bounding-box area across ``axis`` of the lowest ``END_SLAB`` of a body (V, 3) over that of
    its highest: > 1 when the feet (two feet apart, a foot's length deep) are at the low end."""
    h = vertices[:, axis]
    lo, hi = float(h.min()), float(h.max())
    across = [a for a in range(3) if a != axis]

    def area(points):
        e = points[:, across].max(axis=0) - points[:, across].min(axis=0)
        return float(e[0] * e[1])
    top = area(vertices[h >= hi - END_SLAB * (hi - lo)])
    return area(vertices[h <= lo + END_SLAB * (hi - lo)]) / top if top > 0 else 1.0


# Meshes of one folder whose mean edge lengths differ by more than this factor from the median
# are in other units (poses change edge lengths by a few percent; mm vs m is 1000x).
SCALE_TOLERANCE = 10.0
_UNIT_RATIOS = {"mm among meshes in m (or m among mm)": 1000.0, "cm among meshes in m (or m among cm)": 100.0,
                "mm among meshes in cm (or cm among mm)": 10.0, "inches among meshes in m": 1 / 0.0254}


# Faces whose edges estimate a mesh's scale: an even stride of at most this many (the mean over
# 12,000 edges is within ~1 % of the mean over all; units differ by 10x or more).
SCALE_FACES = 4096


def scale_edges(faces: np.ndarray) -> np.ndarray:
    """(E, 2) vertex pairs: the edges of an even stride of at most ``SCALE_FACES`` faces (F, 3)."""
    f = np.asarray(faces)[:: max(1, -(-len(faces) // SCALE_FACES))]
    return np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])


def _mean_edge_length(vertices: np.ndarray, edges: np.ndarray) -> float:
    """Mean length of ``edges`` (E, 2) (``scale_edges``): the mesh's scale, independent of its
    pose."""
    d = vertices[edges[:, 0]] - vertices[edges[:, 1]]
    return float(np.sqrt(np.einsum("ij,ij->i", d, d)).mean())


def _check_common_scale(scales: np.ndarray, paths: list[Path], lines: list[int], source: str) -> None:
    """Refuse a folder whose meshes are not in one length unit: one mesh's mean edge length
    (``scales`` (N,)) ``SCALE_TOLERANCE`` times off the median of them all."""
    median = float(np.median(scales))
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = scales / median if median > 0 else np.where(scales > 0, np.inf, 1.0)
    off = np.flatnonzero(~((ratio <= SCALE_TOLERANCE) & (ratio >= 1 / SCALE_TOLERANCE)))
    if not off.size:
        return
    i = int(off[np.argmax(np.abs(np.log(np.maximum(ratio[off], 1e-300))))])
    r = float(ratio[i])
    size = max(r, 1 / r) if r > 0 else np.inf
    # Bodies of one folder differ in size by up to ~1.5x (short and tall people): the nearest unit
    # ratio within 2x is the guess.
    what, factor = min(_UNIT_RATIOS.items(), key=lambda item: abs(np.log(size / item[1])))
    guess = f"; one mesh in {what}?" if abs(np.log(size / factor)) < np.log(2.0) else ""
    raise DatabaseError(f"{source}, line {lines[i]}: mesh {paths[i]} is {size:.4g}x "
                        f"{'larger' if r > 1 else 'smaller'} than the other meshes (mean edge length {scales[i]:.4g} "
                        f"vs the median {median:.4g}){guess} expected every mesh of the folder in one length unit; "
                        "convert this one to the unit of the others")


# ----------------------------------------------------------------------------------------------
# The database object
# ----------------------------------------------------------------------------------------------

class ScanDatabase:
    """Registered scans of many subjects in many poses, with per-subject labels.

    Attributes
    ----------
    vertices : (N_scans, V, 3) float32 memmap (after ``load``) or array, metres
    faces : (F, 3) int64
    subjects : {column: (n_subjects,) array}; 'subject' ids and 'sex' as str, labels float64
    scans : {'scan': (N,) int64, 'subject': (N,) str, 'pose': (N,) str}
    rotations : (N_scans, J, 3) float32 axis-angle joint rotations, or None
    meta : dict (meta.json); ``meta['joints']`` names the J joints when rotations are present
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, subjects: Mapping, scans: Mapping,
                 meta: Mapping | None = None, rotations: np.ndarray | None = None, *, _checked: bool = False):
        if not _checked:
            vertices, faces, subjects, scans, meta, rotations = validate_database(
                vertices, faces, subjects, scans, meta, rotations)
            faces = faces.astype(np.int64)
        self.vertices = vertices
        self.faces = faces
        self.subjects = dict(subjects)
        self.scans = dict(scans)
        self.meta = dict(meta)
        self.rotations = rotations
        # The folder ``load`` read (None in memory): where its LANDMARKS_FILE would be.
        self.folder: Path | None = None

    # -- constructors -------------------------------------------------------------------------

    @classmethod
    def load(cls, folder: str | os.PathLike, check_values: bool = True) -> "ScanDatabase":
        """Open a database folder; vertices stay on disk (memmap). Validates every file.

        ``check_values=False`` skips the NaN scan of vertices.npy (a full read of the file).
        """
        path = as_path(folder, "database folder")
        db = cls(**load_database_arrays(path, check_values=check_values), _checked=True)
        db.folder = path
        return db

    @classmethod
    def from_meshes(cls, folder: str | os.PathLike, labels_csv: str | os.PathLike,
                    length_unit: str = "m", rest_pose: str | None = None, up: str | None = None,
                    faces: str | os.PathLike | None = None, spelling: str = "api") -> "ScanDatabase":
        """Build an in-memory database from a folder of registered meshes (OBJ, PLY, GLB, STL, or
        NPY vertices) and a labels CSV.

        See ``read_mesh_folder`` for the CSV columns and ``up``, ``faces``; ``length_unit``
        ('m', 'cm', 'mm') is the unit of the mesh coordinates, converted to metres.
        ``rest_pose``: a pose name or 'first' (each subject's first scan), stored in meta.json
        and checked against every subject (``choose_rest_pose``); None stores no rule (the rest
        pose is the pose 'rest'). ``spelling='cli'`` words messages in ``bodyspace import`` flags.
        """
        labels_csv = as_path(labels_csv, "labels CSV")
        parts = read_mesh_folder(as_path(folder, "mesh folder"), labels_csv, length_unit, up=up, faces=faces,
                                 rest_pose=rest_pose, spelling=spelling)
        if rest_pose is not None:
            parts["meta"][REST_POSE_FIELD] = choose_rest_pose(parts["scans"], rest_pose, str(labels_csv))
        return cls(**parts, _checked=True)

    def save(self, folder: str | os.PathLike, overwrite: bool = False,
             extra_files: Mapping[str, str] | None = None) -> Path:
        """Write this database as a folder (atomically); returns the folder path. ``extra_files``:
        name -> text written into it too (``LANDMARKS_FILE``)."""
        return write_database(folder, self.vertices, self.faces, self.subjects, self.scans, self.meta,
                              rotations=self.rotations, joints=self.meta.get("joints"), overwrite=overwrite,
                              extra_files=extra_files)

    @property
    def landmarks_path(self) -> Path | None:
        """The database folder's landmark file (``LANDMARKS_FILE``), or None if it has none."""
        path = None if self.folder is None else self.folder / LANDMARKS_FILE
        return path if path is not None and path.is_file() else None

    # -- sizes --------------------------------------------------------------------------------

    @property
    def n_scans(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[1])

    @property
    def n_subjects(self) -> int:
        return len(self.subjects[SUBJECT_ID_COLUMN])

    @property
    def joints(self) -> list[str] | None:
        return self.meta.get("joints")

    def __len__(self) -> int:
        return self.n_scans

    def __repr__(self) -> str:
        return (f"ScanDatabase({self.n_scans} scans, {self.n_subjects} subjects, {self.n_vertices} vertices, "
                f"template={self.meta.get('template')!r})")

    # -- queries ------------------------------------------------------------------------------

    def scan_subject_index(self) -> np.ndarray:
        """(N_scans,) int64: the row in ``subjects`` of each scan's subject."""
        row_of = {sid: row for row, sid in enumerate(self.subjects[SUBJECT_ID_COLUMN].tolist())}
        return np.fromiter((row_of[sid] for sid in self.scans["subject"].tolist()), dtype=np.int64,
                           count=self.n_scans)

    def label(self, name: str) -> np.ndarray:
        """(N_scans,) value of subject column ``name`` for each scan."""
        if name not in self.subjects:
            raise DatabaseError(f"label '{name}' not found; the database has {', '.join(self.subjects)}")
        return self.subjects[name][self.scan_subject_index()]

    def mesh(self, scan: int) -> np.ndarray:
        """(V, 3) float64 vertices of one scan (read from disk if memory-mapped)."""
        return np.asarray(self.vertices[scan], dtype=np.float64)

    def read(self, rows, dtype=np.float64) -> np.ndarray:
        """(n, V, 3) vertices of scans ``rows`` (n,) int, in the order given, as ``dtype``.

        The rows are read from a memory-mapped database in increasing order (contiguous runs of
        the file), then put back in the order asked for.
        """
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        if rows.size and (rows.min() < 0 or rows.max() >= self.n_scans):
            raise DatabaseError(f"read: scan rows {rows.min()}..{rows.max()}, expected 0..{self.n_scans - 1}")
        order = np.argsort(rows, kind="stable")
        out = np.empty((len(rows),) + tuple(self.vertices.shape[1:]), dtype=dtype)
        if rows.size and self.folder is not None and isinstance(self.vertices, np.memmap):
            # Read from the file (rowfile.read_rows), not through the map: pages touched through a
            # map stay in the process, so a pass over a large database would grow to its size.
            ranked = rows[order]
            runs = np.flatnonzero(np.diff(ranked) != 1) + 1
            layout = npy_layout(self.folder / VERTICES_FILE)
            for run_rows, run_at in zip(np.split(ranked, runs), np.split(np.arange(len(rows)), runs)):
                block = read_rows(self.folder / VERTICES_FILE, int(run_rows[0]), int(run_rows[-1]) + 1, layout)
                out[order[run_at]] = block[run_rows - run_rows[0]]
            return out
        out[order] = self.vertices[rows[order]]
        return out

    def iter_chunks(self, rows, size: int, dtype=np.float64) -> Iterator[tuple[int, np.ndarray]]:
        """``(start, vertices (n, V, 3))`` for consecutive chunks of ``size`` scans of ``rows``;
        the next chunk is read on a second thread while the caller works on this one (a chunk of
        64 scans is ~60 MB of disk reads, overlapped with encoding)."""
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        size = max(1, int(size))
        with ThreadPoolExecutor(1) as reader:
            pending = reader.submit(self.read, rows[:size], dtype)
            for start in range(0, len(rows), size):
                chunk = pending.result()
                if start + size < len(rows):
                    pending = reader.submit(self.read, rows[start + size:start + 2 * size], dtype)
                yield start, chunk

    def select(self, mask_or_indices) -> "ScanDatabase":
        """A new in-memory database with the chosen scans, renumbered, and only their subjects.

        ``mask_or_indices``: (N_scans,) bool mask, or integer scan indices (order kept).
        """
        selection = np.asarray(mask_or_indices)
        if selection.dtype == bool:
            if selection.shape != (self.n_scans,):
                raise DatabaseError(f"select: mask has shape {selection.shape}, expected ({self.n_scans},)")
            indices = np.flatnonzero(selection)
        elif selection.dtype.kind in "iu" or selection.size == 0:
            indices = selection.astype(np.int64).reshape(-1)
            if indices.size and (indices.min() < -self.n_scans or indices.max() >= self.n_scans):
                raise DatabaseError(f"select: scan indices {indices.min()}..{indices.max()}, "
                                    f"expected 0..{self.n_scans - 1}")
            indices = indices % max(self.n_scans, 1)
        else:
            raise DatabaseError(f"select: got dtype {selection.dtype}, expected a bool mask or integer indices")
        # Sorted indices let a memmap read contiguous runs; the order is restored afterwards.
        vertices = self.read(indices, dtype=self.vertices.dtype)  # sorted runs, by pread from a file
        scan_subjects = self.scans["subject"][indices]
        keep = np.isin(self.subjects[SUBJECT_ID_COLUMN], scan_subjects)
        subjects = {name: values[keep] for name, values in self.subjects.items()}
        scans = {"scan": np.arange(len(indices), dtype=np.int64), "subject": scan_subjects,
                 "pose": self.scans["pose"][indices]}
        rotations = None if self.rotations is None else np.array(self.rotations[indices])
        meta = build_meta(self.meta, vertices.shape, len(self.faces), self.meta.get("joints"))
        return ScanDatabase(vertices, self.faces.copy(), subjects, scans, meta, rotations, _checked=True)

    def rest_rows(self) -> np.ndarray:
        """(n,) int64 rows of the rest-pose scans (rest_pose_rows with this database's meta)."""
        return rest_pose_rows(self.scans, self.meta)

    def rest_pose(self) -> "ScanDatabase":
        """The scans in the rest pose (``meta['rest_pose']``, default pose 'rest')."""
        rows = self.rest_rows()
        if not len(rows):
            raise DatabaseError(f"no scan has pose '{rest_pose_name(self.meta)}'; poses present: "
                                f"{', '.join(sorted(set(self.scans['pose'].tolist()))[:10])}")
        return self.select(rows)


def rest_pose_name(meta: Mapping) -> str:
    """The rest pose a database's meta names: a pose name, or REST_POSE_FIRST."""
    rule = meta.get(REST_POSE_FIELD) or {}
    if rule.get(REST_POSE_FIRST):
        return REST_POSE_FIRST
    return str(rule.get("pose", REST_POSE))


def rest_pose_rows(scans: Mapping[str, np.ndarray], meta: Mapping) -> np.ndarray:
    """(n,) int64 rows of the rest-pose scans: those of the pose ``meta['rest_pose']`` names
    (default REST_POSE), or each subject's first scan when it says ``{"first": true}``."""
    rule = meta.get(REST_POSE_FIELD) or {}
    if rule.get(REST_POSE_FIRST):
        _, first = np.unique(np.asarray(scans["subject"]), return_index=True)
        return np.sort(first).astype(np.int64)
    return np.flatnonzero(np.asarray(scans["pose"]) == str(rule.get("pose", REST_POSE))).astype(np.int64)


def choose_rest_pose(scans: Mapping[str, np.ndarray], rest_pose: str | None, source: str) -> dict:
    """The meta ``rest_pose`` rule for an import: ``rest_pose`` a pose name, REST_POSE_FIRST, or
    None (REST_POSE if every subject has a scan of it). Raises DatabaseError when a subject has no
    scan of the chosen pose."""
    if rest_pose == REST_POSE_FIRST:
        return {REST_POSE_FIRST: True}
    name = REST_POSE if rest_pose is None else str(rest_pose)
    subjects = np.asarray(scans["subject"])
    having = set(subjects[np.asarray(scans["pose"]) == name].tolist())
    lacking = [sid for sid in dict.fromkeys(subjects.tolist()) if sid not in having]
    if lacking:
        poses = sorted(set(np.asarray(scans["pose"]).tolist()))
        fix = ("pass --rest-pose NAME (one of the poses) or --rest-pose first (each subject's first scan)"
               if rest_pose is None else "choose another --rest-pose, or --rest-pose first")
        raise DatabaseError(f"{source}: subject(s) {', '.join(map(repr, lacking[:5]))}{' ...' if len(lacking) > 5 else ''}"
                            f" have no scan of pose '{name}' (poses: {', '.join(poses[:10])}"
                            f"{' ...' if len(poses) > 10 else ''}); {fix}")
    return {"pose": name}
