"""``bodyspace measure``: measure meshes with the default measurement set, a model's (``--model``),
or a landmark file's."""

from __future__ import annotations

import csv
import io
import json
import time
from pathlib import Path
from typing import Optional

import numpy as np
import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from bodyspace.atomic import atomic_path
from bodyspace.cli.common import ForceOption, check_file_output, console, progress
from bodyspace.data.database import META_FILE, VERTICES_FILE, ScanDatabase
from bodyspace.data.template import load_template
from bodyspace.errors import BodyspaceError, MeasurementError, MeshError, UnposeError
from bodyspace.measure import check_compatible, conventions, evaluate, load_measurement_set, to_json
from bodyspace.measure.definitions import standing_note, with_standing_body
from bodyspace.measure.landmark_check import landmark_measurement_set
from bodyspace.mesh.io import load_mesh
from bodyspace.model import BodyModel
from bodyspace.parallel import in_order
from bodyspace.report.measured import measured_bodies_figure
from bodyspace.rig.unpose import KNOWN_POSE_TOLERANCE, fits_template, unpose, unpose_known
from bodyspace.rowfile import npy_layout, read_rows


def measure(meshes: list[Path] = typer.Argument(..., help="Mesh files (OBJ/PLY/GLB), metres, +Y up (else say so with "
                                                "--units/--up). A file given twice is measured twice (its second "
                                                "column is 'NAME (2)')."),
            landmarks: Optional[Path] = typer.Option(None, "--landmarks", help="Landmark file for another topology "
                                                     "(JSON {\"landmarks\": {name: vertex id or {\"vertices\": [...], \"weights\": [...]}}}, "
                                                     "at most 25 names; docs/measurements.md)."),
            model: Optional[Path] = typer.Option(None, "--model", help="Measure with the measurement set a model file "
                                                 "carries (bodyspace build; its topology's landmarks). Not with "
                                                 "--landmarks."),
            json_out: bool = typer.Option(False, "--json", help="Print JSON: name → {value, unit, note?} (several meshes: mesh → name → ...); "
                                          "an undefined value is null and its note says why. Not with --csv."),
            csv_out: bool = typer.Option(False, "--csv", help="Print CSV: mesh,name,value,unit,note "
                                         "(note: why a value is empty). Not with --json. A scan database "
                                         "(bodyspace population / import) is measured into a file instead: "
                                         "bodyspace measure DB --csv FILE.csv writes one row per scan with its "
                                         "subject and pose, streamed in chunks."),
            png: Optional[Path] = typer.Option(None, "--png", help="Draw the measured lines (front and side) to "
                                               "this PNG file (refused if it exists, unless --force)."),
            units: Optional[str] = typer.Option(None, "--units", help="The meshes' length unit: m, cm, mm or in "
                                                "(inches). Default: metres; a mesh in other units is refused with "
                                                "the --units to give."),
            up: Optional[str] = typer.Option(None, "--up", help="The meshes' up axis: y, -y (upside down), x, -x, z "
                                             "(Z up, facing -Y, as Blender) or -z. Default: +Y; a mesh standing "
                                             "along another axis is refused with the --up to give."),
            flip_winding: bool = typer.Option(False, "--flip-winding", help="Reverse every face: for meshes whose "
                                              "faces are wound inwards (negative volume; refused without it)."),
            as_posed: bool = typer.Option(False, "--as-posed", help="Measure the mesh as it is, the tape on the posed "
                                          "body. By default a mesh of the template's topology is first brought back "
                                          "to the rest pose (docs/unposing.md) and measured standing."),
            force: bool = ForceOption):
    """Measure body meshes: ISO 8559-1 girths and lengths, Rupprecht's six, volume, mass, BMI."""
    if meshes and is_database(meshes[0]):
        try:
            # `measure DB --csv FILE.csv`: --csv is a flag (meshes print CSV), so FILE.csv arrives
            # as a second argument.
            csv_file = _database_csv_file(meshes, csv_out)
            measure_database(meshes[0], csv_file, landmarks=landmarks, model=model, json_out=json_out, png=png,
                             units=units, up=up, flip_winding=flip_winding, as_posed=as_posed, force=force)
        except BodyspaceError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(code=2)
        return
    try:
        _check_outputs(json_out, csv_out, png, force, meshes)
        if model is not None and landmarks is not None:
            raise MeasurementError("--model and --landmarks were both given; give one (the model's measurement "
                                   "set, or a landmark file)")
        words = _convention_flags(landmarks)
        conventions.check_arguments(units, up, words)
        mset = load_measurement_set() if model is None else model_measurement_set(model)
        if landmarks is not None:        # with the parts and joints bodyspace landmarks carries, if any
            mset = landmark_measurement_set(landmarks, base=mset)
        labels = _labels([str(p) for p in meshes])
        results, bodies, postures, left_out = {}, [], {}, {}
        for path, label in zip(meshes, labels):
            v, f = load_mesh(path)
            _check_vertex_count(path, len(v), mset, landmarks, model)
            check_compatible(mset, v, f, str(path))
            # A scanner's floor, turntable or pole left out (said under the output): they would
            # add to the volume, mass and stature, and make the mesh fit no unit.
            body = conventions.body_faces(v, f, mset, units)
            v, f = body.vertices, body.faces
            if body.notes:
                left_out[label] = {"value": round(body.left_out_area, 4), "unit": "m^2",
                                   "note": "; ".join(body.notes)}
            # Off by a convention (mm, Z up, faces inwards, another vertex order): refused with
            # the flag that fixes it, or brought into metres, +Y up as the flags say.
            v, f = conventions.prepare(v, f, mset, str(path), units=units, up=up, flip_winding=flip_winding,
                                       words=words)
            v, postures[label] = _standing(v, f, path, as_posed)
            bodies.append((v, f))
        # A landmark file without body parts or joints for its topology: the first mesh that stands
        # places them for all (a seated body cannot: its arms lie against its torso); else each
        # mesh places its own joints, and its girths are NaN with the reason if it does not stand.
        standing = next(((v, f) for v, f in bodies if standing_note(mset, v) is None), None)
        if standing is not None:
            mset = with_standing_body(mset, *standing)
        for (path, label), (v, f) in zip(zip(meshes, labels), bodies):
            own = with_standing_body(mset, v, f)     # the set itself once a standing mesh placed all
            results[label] = evaluate(own, v, f, keep_polylines=png is not None, mesh_name=str(path))
        if png is not None:
            try:
                measured_bodies_figure(png, bodies, list(results.values()), mset, _column_names(meshes))
            except OSError as exc:   # a folder in the way, no permission, disk full
                raise MeasurementError(f"--png {png}: could not write the picture ({exc.strerror or exc}); "
                                       "choose a writable file path") from None
    except BodyspaceError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(code=2)
    rows = {label: to_json(r) for label, r in results.items()}
    for label, posture in postures.items():
        if posture is not None:
            rows[label]["unposed"] = posture
    if left_out:      # every mesh gets the row (the table's rows are the first mesh's)
        for label in rows:
            rows[label]["left_out"] = left_out.get(label, {"value": 0.0, "unit": "m^2",
                                                          "note": "nothing left out: the mesh is all body"})
    if csv_out:
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow(["mesh", "name", "value", "unit", "note"])
        for label, row in rows.items():
            for name, e in row.items():
                w.writerow([label, name, "" if e["value"] is None else e["value"], e["unit"], e.get("note", "")])
        typer.echo(buf.getvalue().rstrip("\n"))
    elif json_out:
        # allow_nan=False: NaN or Infinity would not be JSON; to_json already made them null + note.
        typer.echo(json.dumps(rows[labels[0]] if len(meshes) == 1 else rows, indent=2, allow_nan=False))
    else:
        _print_table(rows, _column_names(meshes))
        for name, posture in zip(_column_names(meshes), postures.values()):
            if posture is not None and posture["value"] is not None:
                Console().print(f"[unposed] {name}: {posture['note']}", markup=False, highlight=False)
        for name, label in zip(_column_names(meshes), labels):
            if label in left_out:
                Console().print(f"[left out] {name}: {left_out[label]['note']}", markup=False, highlight=False)


def _standing(vertices: np.ndarray, faces: np.ndarray, path: Path, as_posed: bool) -> tuple[np.ndarray, dict | None]:
    """The body to measure and what the output says about its pose (an entry {value, unit, note}).

    A mesh of the template's topology (its vertex count, its faces or a subset of them: holes are
    fine) is unposed with the template's default rig and measured standing; ``--as-posed``
    measures the mesh as it is (no entry). Any other mesh is measured as posed, with a note.
    """
    if as_posed:
        return vertices, None
    template = load_template()
    if not fits_template(vertices, faces, template):
        return vertices, {"value": None, "unit": "deg",
                          "note": f"not unposed: only meshes of the template's topology ({template.n_vertices} "
                                  f"vertices in its order) have a rig, this one has {len(vertices)} vertices"
                                  f"{'' if len(vertices) != template.n_vertices else ' and other faces'}; "
                                  "measured as posed"}
    try:
        rest, _, info = unpose(vertices, template.rigs["default"], mesh_name=str(path))
    except UnposeError as exc:
        raise UnposeError(f"{exc} (--as-posed measures the mesh as it is, without unposing)") from None
    return rest, {"value": round(float(info.largest_rotation_deg), 1), "unit": "deg",
                  "note": f"measured standing: the body was brought back to the rest pose first ({info.describe()}); "
                          "--as-posed measures the mesh as it is"}


def _check_outputs(json_out: bool, csv_out: bool, png: Path | None, force: bool, meshes: list[Path]) -> None:
    """Refuse conflicting or unsafe outputs before any work (MeasurementError in CLI words)."""
    if json_out and csv_out:
        raise MeasurementError("--json and --csv were both given, but both print to standard output; "
                               "give one of them (run twice for both)")
    for flag, given, suffix in (("--json", json_out, ".json"), ("--csv", csv_out, ".csv")):
        named = [p for p in meshes if given and p.suffix.lower() == suffix]
        if named:
            # `--json out.json` reads out.json as a mesh; say what the flag does instead.
            raise MeasurementError(f"{named[0]}: {flag} takes no file name, it prints {suffix[1:].upper()} to the "
                                   f"terminal; to keep it in a file, redirect: bodyspace measure MESHES {flag} > "
                                   f"{named[0]}")
    if png is None:
        return
    check_file_output(png, "--png", force, (".png",), example="measurements.png")
    if any(png.resolve() == p.resolve() for p in meshes):
        raise MeasurementError(f"--png {png}: is one of the meshes to measure; choose another file name")


def _check_vertex_count(path: Path, n_vertices: int, mset, landmarks: Path | None, model: Path | None = None) -> None:
    """The mesh's vertex count must be the set's, said in the flags that fix it."""
    if mset.n_vertices is None or n_vertices == mset.n_vertices:
        return
    if Path(path).suffix.lower() == ".stl":
        # STL keeps no vertex ids: every triangle lists its own corners (a 7,002-vertex body came
        # back with 42,000, and the refusal asked for another landmark file).
        raise MeasurementError(f"{path}: an STL file stores each triangle's corners ({n_vertices} here), not the mesh's "
                               f"shared, numbered vertices, so no landmark file or model (made for meshes of "
                               f"{mset.n_vertices} vertices) can name its points; export the mesh as OBJ or PLY "
                               "keeping its vertex order, and measure that")
    if model is not None:
        raise MeasurementError(f"{path}: {n_vertices} vertices, but the model --model {model} is of meshes of "
                               f"{mset.n_vertices} vertices (its measurement set, from {mset.source}); measure meshes "
                               "of the model's topology, or give this mesh's landmarks with --landmarks FILE instead")
    if landmarks is None:
        raise MeasurementError(f"{path}: {n_vertices} vertices, but the default measurement set "
                               f"({Path(mset.source).name}) is for meshes of the {mset.template or 'default'} "
                               f"template, {mset.n_vertices} vertices in its order; to measure a mesh of another "
                               "topology give its landmarks with --landmarks FILE (docs/measurements.md)")
    raise MeasurementError(f"{path}: {n_vertices} vertices, but the landmark file --landmarks {landmarks} says "
                           f"n_vertices {mset.n_vertices}; give the landmark file made for this mesh's topology "
                           "(or remove its n_vertices)")


def _convention_flags(landmarks: Path | None) -> dict:
    """The fixes of ``conventions.prepare`` in this command's flags."""
    order = (f"the landmark file of this mesh's vertex order with --landmarks FILE (not {landmarks})" if landmarks
             else "--landmarks FILE, the landmark file of this mesh's vertex order, or save the mesh in the "
                  "template's vertex order")
    return {"units": "--units {}", "up": "--up {}", "flip_winding": "--flip-winding", "landmarks": order}


def model_measurement_set(path: Path):
    """The measurement set a model file carries (``BodyModel.measurement_set``), said in CLI words
    when it has none."""
    mset = BodyModel.read_measurement_set(path)
    if mset is None:
        raise MeasurementError(f"--model {path}: carries no measurement set (its topology is not the template's and "
                               "it was built without landmarks); build it with bodyspace build DB --landmarks FILE, "
                               "or measure with --landmarks FILE")
    return mset


def _labels(names: list[str]) -> list[str]:
    """One label per input, in order: a name given again is labelled by its position, 'a.obj (2)'."""
    seen: dict[str, int] = {}
    out = []
    for name in names:
        seen[name] = seen.get(name, 0) + 1
        out.append(name if seen[name] == 1 else f"{name} ({seen[name]})")
    return out


def _column_names(meshes: list[Path]) -> list[str]:
    """Short labels for the table and the picture: file names, or the paths where two files
    share a name; repeats labelled by position as in ``_labels``."""
    short = len({p.name for p in meshes}) == len({str(p) for p in meshes})
    return _labels([p.name if short else str(p) for p in meshes])


def _print_table(rows: dict[str, dict], headers: list[str]) -> None:
    """One column per mesh; an undefined value is 'n/a [k]', its reason printed under the table, and
    a value with a note 'VALUE [k]' (the note under the table too)."""
    table = Table(title="measurements")
    table.add_column("name")
    for h in headers:
        table.add_column(escape(h), justify="right")
    table.add_column("unit")
    reasons: dict[str, int] = {}
    for name, first in next(iter(rows.values())).items():
        cells = []
        for row in rows.values():
            e = row[name]
            if e["value"] is None:
                k = reasons.setdefault(e.get("note") or "undefined for this body", len(reasons) + 1)
                cells.append(escape(f"n/a [{k}]"))
            elif e.get("note") and name not in ("unposed", "left_out"):    # a caveat (a landmark in a hole); the
                # unposed and left_out rows' notes are printed under the table on their own lines
                k = reasons.setdefault(e["note"], len(reasons) + 1)
                cells.append(escape(f"{e['value']:.4g} [{k}]"))
            else:
                cells.append(f"{e['value']:.4g}")
        table.add_row(escape(name), *cells, escape(first["unit"]))
    console = Console()
    console.print(table)
    for why, k in reasons.items():
        console.print(f"[{k}] {why}", markup=False, highlight=False)


# ----------------------------------------------------------------------------- a scan database
# Scans per chunk of `measure DB --csv FILE`: read, unposed and measured together in one worker
# (about 60 MB of float64 vertices and the unposing's temporaries), written in scan order.
DB_CHUNK = 128
DB_WORKERS = 2
# The CSV column suffix of each display unit (the label convention of scan databases: the unit
# ends the name, so the file can be read back as labels).
_UNIT_SUFFIX = {"cm": "cm", "kg": "kg", "m^3": "m3", "m^2": "m2", "kg/m^2": "kg_m2", "%": "percent", "deg": "deg",
                "1": "1"}
# What forked workers inherit (set before the pool forks, so no chunk of vertices is pickled).
_DB_JOB: dict = {}


def is_database(path: Path) -> bool:
    """A scan database folder (it holds the database's meta.json), not a mesh file."""
    return path.is_dir() and (path / META_FILE).is_file()


def _database_csv_file(arguments: list[Path], csv_flag: bool) -> Path | None:
    """The CSV file of ``measure DB --csv FILE.csv`` (the arguments after the database), or None
    when none was given; anything else beside a database is refused."""
    folder, rest = arguments[0], arguments[1:]
    if not rest:
        return None
    if len(rest) == 1 and rest[0].suffix.lower() == ".csv" and csv_flag:
        return rest[0]
    raise MeasurementError(f"{folder} is a scan database and is measured alone into a CSV file (bodyspace measure "
                           f"{folder} --csv FILE.csv); found {' '.join(map(str, rest))} beside it"
                           + ("" if csv_flag else " without --csv"))


def measure_database(folder: Path, csv_out: Path | None, *, landmarks: Path | None, model: Path | None,
                     json_out: bool, png: Path | None, units: str | None, up: str | None, flip_winding: bool,
                     as_posed: bool, force: bool, chunk: int = DB_CHUNK, workers: int = DB_WORKERS) -> None:
    """``bodyspace measure DB --csv FILE``: every scan of a database, one CSV row per scan.

    Columns: scan, subject, pose, unposed_deg (the largest turn undone, empty for scans measured as
    they are), one column per measurement named with its unit (``chest_girth_cm``), and note
    (why a value is empty). Chunks of ``chunk`` scans are read from the file, unposed (unless
    ``--as-posed``; scans whose recorded rotations are all zero are standing already) and measured
    in ``workers`` forked processes, and written in scan order to a temporary file renamed onto
    FILE at the end: memory does not grow with the database, and a killed run leaves no FILE.
    """
    for given, flag in ((json_out, "--json"), (png is not None, "--png"), (units is not None, "--units"),
                        (up is not None, "--up"), (flip_winding, "--flip-winding")):
        if given:
            why = ("a database is in metres, +Y up, with its faces checked when it was written"
                   if flag in ("--units", "--up", "--flip-winding") else "a database is measured into a CSV file")
            raise MeasurementError(f"{folder} is a scan database; {flag} does not apply ({why}); "
                                   f"run bodyspace measure {folder} --csv FILE")
    if csv_out is None:
        raise MeasurementError(f"{folder} is a scan database: its scans are measured into a CSV file, one row per "
                               f"scan; give the file with --csv FILE (e.g. bodyspace measure {folder} --csv "
                               "measurements.csv)")
    out = csv_out
    check_file_output(out, "--csv", force, (".csv",), example="measurements.csv")
    if model is not None and landmarks is not None:
        raise MeasurementError("--model and --landmarks were both given; give one (the model's measurement "
                               "set, or a landmark file)")
    db = ScanDatabase.load(folder, check_values=False)
    landmarks = landmarks if landmarks is not None or model is not None else db.landmarks_path
    mset = load_measurement_set() if model is None else model_measurement_set(model)
    if landmarks is not None:
        mset = landmark_measurement_set(landmarks, base=mset)
    _check_vertex_count(folder / "vertices.npy", db.n_vertices, mset, landmarks, model)
    check_compatible(mset, db.read([0])[0], db.faces, str(folder))
    rest = db.rest_rows()
    if landmarks is not None and len(rest):
        # Body parts and the neck's joints placed on the first rest scan: every scan is then cut
        # by the parts of a standing body, and its neck girth's plane leans with its neck.
        mset = with_standing_body(mset, db.read(rest[:1])[0], db.faces)
    template = load_template()
    unposable = not as_posed and fits_template(db.read([0])[0], db.faces, template)
    columns, names = _database_columns(mset, unposable)
    ages, males = _scan_demographics(db)
    rig = template.rigs["default"] if unposable else None
    # Rotations recorded for this rig's bones (by name) are the pose to undo (``unpose_known``).
    known_pose = (rig is not None and db.rotations is not None
                  and list(db.meta.get("joints") or []) == list(rig.bone_names))
    _DB_JOB.update(db=db, mset=mset, rig=rig, ages=ages, males=males, known_pose=known_pose)
    n = db.n_scans
    if workers > 1 and n > 1:
        # One scan here first: the template, the unposing plan and the compiled kernels are then
        # loaded once and inherited by the forked workers (each loaded its own: ~2 s CPU a worker).
        _measure_chunk(0, 1)
    chunk = max(1, min(chunk, -(-n // (2 * workers))))  # a small database still keeps both workers busy
    starts = list(range(0, n, chunk))
    measured = undefined = 0
    started = time.perf_counter()
    try:
        with progress("measure", eta=True) as cb, atomic_path(out) as tmp:
            with open(tmp, "w", newline="", encoding="utf-8") as handle:
                writer = csv.writer(handle)
                writer.writerow(columns)
                spans = ((start, min(n, start + chunk)) for start in starts)
                results = in_order(_measure_chunk, spans, workers if len(starts) > 1 else 1,
                                   died=f"run bodyspace measure {folder} --csv {out} again")
                for start, (values, degrees, notes) in zip(starts, results):
                    stop = start + len(values)
                    subjects, poses = db.scans["subject"][start:stop].tolist(), db.scans["pose"][start:stop].tolist()
                    for i, cells in enumerate(_cells(values, degrees)):
                        writer.writerow([start + i, subjects[i], poses[i]] + cells + [notes[i]])
                    measured += len(values)
                    undefined += int(np.isnan(values).any(axis=1).sum())
                    cb(f"{measured}/{n} scans", measured / n)
    finally:
        _DB_JOB.clear()
    wall = time.perf_counter() - started
    console.print(f"wrote {out}: {n} scans x {len(names)} measurements of {db!r} in {wall:.1f} s "
                  f"({n / max(wall, 1e-9):.0f} scans/s); {'unposed first' if unposable else 'measured as posed'}; "
                  f"{undefined} scan(s) with an empty value (see the note column)", highlight=False, soft_wrap=True)


def _database_columns(mset, unposable: bool) -> tuple[list[str], list[str]]:
    """The CSV header and the measurement names, in the set's order."""
    names = list(mset.names)
    units = {m["name"]: m["unit"] for m in mset.measurements}
    unit_of = {"m": "cm"}  # lengths are written in cm, as everywhere on the CLI
    cols = [f"{name}_{_UNIT_SUFFIX.get(unit_of.get(units[name], units[name]), 'value')}" for name in names]
    return ["scan", "subject", "pose"] + (["unposed_deg"] if unposable else []) + cols + ["note"], names


def _scan_demographics(db: ScanDatabase) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(age years, male) per scan from the subjects table when it has them (mass from volume
    depends on them, composition.py), else None (the set's defaults)."""
    row = db.scan_subject_index()
    ages = db.subjects["age_years"][row] if "age_years" in db.subjects else None
    if ages is not None and np.isnan(ages).any():
        ages = None
    males = (db.subjects["sex"][row] == "male") if "sex" in db.subjects else None
    return ages, males


def _cells(values: np.ndarray, degrees: np.ndarray | None) -> list[list[str]]:
    """The number cells of a chunk's CSV rows: the unposed angle (n,) to 0.1 degree (if any) and
    the values (n, M) to 4 decimals, empty where not finite. One C-level format a row (a Python
    f-string a cell cost the parent 0.1 ms a scan, 5 % of the command)."""
    table = values if degrees is None else np.column_stack([degrees, values])
    table = np.where(np.isfinite(table), table, np.nan)          # inf too: empty, not "inf"
    fmt = ",".join((["%.1f"] if degrees is not None else []) + ["%.4f"] * values.shape[1])
    # "%f" writes a NaN as "nan" (never signed), and no other cell holds those letters.
    return [(fmt % tuple(row)).replace("nan", "").split(",") for row in table.tolist()]


def _read_chunk(db: ScanDatabase, start: int, stop: int, order: np.ndarray) -> np.ndarray:
    """Scans ``start..stop`` of ``db`` as float64 (n, V, 3), in the order ``order`` (n,), read into
    buffers this process keeps from chunk to chunk (one ``pread`` of the rows, then a gather and
    a conversion in place): a chunk's fresh 60 MB cost ~0.1 ms a scan of page faults. The array
    is overwritten by the next chunk (nothing of it outlives ``_measure_chunk``)."""
    if db.folder is None or not isinstance(db.vertices, np.memmap):
        return db.read(start + order)
    buffers = _DB_JOB.setdefault("buffers", {})
    path = db.folder / VERTICES_FILE
    if "layout" not in buffers:
        buffers["layout"] = npy_layout(path)
    shape, dtype = buffers["layout"][:2]
    n = stop - start
    if buffers.get("capacity", 0) < n:
        buffers.update(capacity=n, raw=np.empty((n,) + tuple(shape[1:]), dtype=dtype),
                       sorted=np.empty((n,) + tuple(shape[1:]), dtype=dtype),
                       out=np.empty((n,) + tuple(shape[1:])))
    raw = read_rows(path, start, stop, buffers["layout"], out=buffers["raw"][:n])
    np.take(raw, order, axis=0, out=buffers["sorted"][:n])
    out = buffers["out"][:n]
    out[...] = buffers["sorted"][:n]
    return out


def _measure_chunk(start: int, stop: int) -> tuple[np.ndarray, np.ndarray | None, list[str]]:
    """Scans ``start..stop`` of the database in ``_DB_JOB``: values (n, M) in display units, the
    unposed angle (n,) or None, and each scan's note ('' when every value is defined)."""
    db, mset, rig = _DB_JOB["db"], _DB_JOB["mset"], _DB_JOB["rig"]
    rows = np.arange(start, stop)
    posed = np.ones(len(rows), dtype=bool)
    if rig is not None and db.rotations is not None:
        posed = np.abs(np.asarray(db.rotations[start:stop])).max(axis=(1, 2)) > 0
    known = rig is not None and _DB_JOB["known_pose"]
    # With the recorded rotations the posed scans are read first (rows ``order``), so they are
    # unposed in place as one block: no (n, V, 3) gather of them and scatter back (two copies
    # of ~33 MB a chunk). The results are put back in scan order at the end.
    order = np.r_[np.flatnonzero(posed), np.flatnonzero(~posed)] if known else np.arange(len(rows))
    rows = rows[order]
    posed = posed[order]
    v = _read_chunk(db, start, stop, order)
    notes = [[] for _ in rows]
    degrees = None
    if rig is not None:
        degrees = np.zeros(len(rows))
        todo = np.flatnonzero(posed)
        if todo.size and known:
            # The database recorded the rotations that posed each scan (bodyspace population):
            # inverse skinning with them is exact and ~30x cheaper than estimating the pose. A scan
            # they do not explain (its rest body off the rest-shape space) is fitted below.
            k = todo.size                                                      # todo == arange(k)
            _, _, info = unpose_known(v[:k], rig, np.asarray(db.rotations)[rows[:k]],
                                      mesh_name=f"scans {start}..{stop - 1}", in_place=True)
            ok = info.shape_distance_m <= KNOWN_POSE_TOLERANCE
            degrees[:k][ok] = info.largest_rotation_deg[ok]
            todo = todo[~ok]
            if todo.size:                                   # unposed in place: read them again
                v[todo] = db.read(rows[todo])
        try:
            if todo.size:
                rest, _, info = unpose(v[todo], rig, mesh_name=f"scans {start}..{stop - 1}")
                v[todo], degrees[todo] = rest, info.largest_rotation_deg
        except MeshError:
            for i in todo:  # one scan the fit refuses: the others of its chunk are still unposed
                try:
                    rest, _, info = unpose(v[i], rig, mesh_name=f"scan {rows[i]}")
                except MeshError as exc:
                    notes[i].append(f"not unposed ({exc}); measured as posed")
                    degrees[i] = np.nan
                    continue
                v[i], degrees[i] = rest, float(info.largest_rotation_deg)
    ages = None if _DB_JOB["ages"] is None else _DB_JOB["ages"][rows]
    males = None if _DB_JOB["males"] is None else _DB_JOB["males"][rows]
    values = np.empty((len(rows), len(mset.names)))
    # One evaluate for the chunk: the mass method takes one sex and one age per body.
    # The chunk in one piece (evaluate's own chunks would halve it: its per-chunk Python is a
    # fixed cost, ~0.1 ms a scan at 64 scans).
    results = evaluate(mset, v, db.faces, age_years=ages, male=None if males is None else males.astype(float),
                       mesh_name=f"scans {start}..{stop - 1}", chunk=max(1, len(v)))
    for j, m in enumerate(results.values()):
        values[:, j] = m.display()[0]
        for i, why in enumerate(m.note or []):
            if why and not np.isfinite(values[i, j]):
                notes[i].append(f"{m.name}: {why}")
    back = np.argsort(order)                                                   # scan order again
    return (values[back], None if degrees is None else degrees[back],
            ["; ".join(dict.fromkeys(notes[i])) for i in back])
