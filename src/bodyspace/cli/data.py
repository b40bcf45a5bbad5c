"""``bodyspace import``: a scan database from a user's own folder of registered meshes and a
labels CSV (``ScanDatabase.from_meshes``), without writing Python; with ``--register``, from a
folder of raw scans, each registered to the template first (``register.batch``)."""

from __future__ import annotations

import csv
import io
import tempfile
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from bodyspace.cli.common import ForceOption, check_choice, check_folder_output, console, out_console, progress
from bodyspace.cli.register import registration_model
from bodyspace.data.database import (
    DATABASE_KIND,
    LANDMARKS_FILE,
    MESH_COLUMN,
    REST_POSE_FIELD,
    REST_POSE_FIRST,
    SEX_COLUMN,
    SUBJECT_ID_COLUMN,
    ScanDatabase,
    check_label_columns,
    choose_rest_pose,
    read_csv_columns,
    rest_pose_rows,
)
from bodyspace.data.template import load_template
from bodyspace.errors import DatabaseError
from bodyspace.measure import load_landmarks, load_measurement_set
from bodyspace.measure.conventions import MESH_UNITS, UP_ROTATIONS, standing_placement
from bodyspace.model import check_landmark_file
from bodyspace.register.batch import register_files
from bodyspace.register.pipeline import DEFAULT_STEPS

LENGTH_UNITS = ("m", "cm", "mm")
# A fit whose joint is turned more than this from the template's rest (A-)pose is not standing in
# the rest pose (measured on the user walk's scans: a rest-pose scan fits at 2.4° at most, a
# T-pose at 45°; people asked for the A-pose stand within some 15° of it).
POSED_DEGREES = 25.0
# The per-scan report ``import --register`` writes into the database folder.
REGISTRATION_REPORT = "registration.csv"


def import_meshes(mesh_folder: Path = typer.Argument(..., help="Folder of registered meshes of one topology: OBJ, "
                                                               "PLY, GLB, STL, or NPY files of (V, 3) vertices."),
                  labels: Path = typer.Option(..., "--labels",
                                              help="CSV: a 'mesh' column (file name in MESH_FOLDER), optional "
                                                   "'subject', 'pose', 'sex', and labels named with their unit "
                                                   "(stature_cm, mass_kg, waist_girth_cm, ...)."),
                  out: Path = typer.Option(..., "--out", help="Scan database folder to write (see --force)."),
                  rest_pose: Optional[str] = typer.Option(
                      None, "--rest-pose",
                      help="The pose that counts as the rest pose (build --selection rest): a pose name, or "
                           "'first' (each subject's first mesh in the CSV). Default: 'rest' if every subject "
                           "has it."),
                  units: Optional[str] = typer.Option(None, "--units", help="Length unit of the mesh coordinates: m, "
                                                      "cm or mm (stored in metres); default m. With --register: "
                                                      "the scans' unit (m, cm, mm, in), default found per scan."),
                  landmarks: Optional[Path] = typer.Option(
                      None, "--landmarks", help="Landmark file of the meshes' topology (docs/measurements.md): "
                                                "checked on the rest scans and copied into the database as "
                                                "landmarks.json, so bodyspace build gives the model its measurements."),
                  up: Optional[str] = typer.Option(
                      None, "--up", help="The meshes' up axis: y, -y, z, -z, x or -x (stored +Y up). Default: +Y, "
                                         "checked (a folder standing along another axis is refused)."),
                  faces: Optional[Path] = typer.Option(
                      None, "--faces", help="The faces of NPY meshes: a mesh file of the same topology, or an (F, 3) "
                                            "integer .npy. Default: the first mesh of the CSV that has faces."),
                  register: bool = typer.Option(False, "--register", help="MESH_FOLDER holds raw scans (point clouds "
                                                "or meshes in any frame, PLY/OBJ/STL/GLB/XYZ/TXT/CSV/NPY): register "
                                                "each to the template first (as bodyspace register; landmarks from "
                                                "NAME.lnd or NAME.landmarks.json beside a scan). Scans refused by "
                                                "quality are listed with the reason and left out."),
                  model: Optional[Path] = typer.Option(None, "--model", help="With --register: a BodyModel file of "
                                                       "the template's topology whose shape space the fits use."),
                  steps: int = typer.Option(DEFAULT_STEPS, "--steps", min=1, max=40, help="With --register: stiffness "
                                            "levels of the non-rigid refinement."),
                  keep_placement: bool = typer.Option(
                      False, "--keep-placement", help="With --landmarks: keep the meshes where they stand and the "
                                                      "way they face. Default: turned about the vertical to face +Z "
                                                      "and moved onto the floor over the origin (one move for the "
                                                      "folder, from the rest scans' shoulder and hip joints)."),
                  force: bool = ForceOption):
    """Import a folder of your own registered meshes (or, with --register, raw scans) and a labels CSV as a scan
    database."""
    if register:
        return _import_scans(mesh_folder, labels, out, rest_pose=rest_pose, units=units, up=up, landmarks=landmarks,
                             faces=faces, model=model, steps=steps, force=force)
    if model is not None or steps != DEFAULT_STEPS:
        raise DatabaseError(f"{'--model' if model is not None else '--steps'} is used with --register (raw scans "
                            "are fitted with it); registered meshes are imported as they are")
    units = check_choice(units or "m", "--units", LENGTH_UNITS)
    if up is not None:
        up = check_choice(up, "--up", UP_ROTATIONS)
    check_folder_output(out, "--out", force, DATABASE_KIND)  # a bad --out is said before reading meshes
    with progress("import") as cb:
        cb(f"reading meshes of {mesh_folder}", 0.0)
        db = ScanDatabase.from_meshes(mesh_folder, labels, length_unit=units, rest_pose=rest_pose, up=up,
                                      faces=faces, spelling="cli")
        rule = choose_rest_pose(db.scans, rest_pose, str(labels))
        db.meta[REST_POSE_FIELD] = rule
        db.meta["provenance"]["source"] = "bodyspace import"
        extra = {}
        placed = None
        if landmarks is not None:
            cb(f"checking {landmarks} on the rest scans", 0.7)
            extra[LANDMARKS_FILE] = check_landmark_file(landmarks, db)
            if not keep_placement:
                placed = _place(db, landmarks)
        cb(f"writing {out}", 0.8)
        db.save(out, overwrite=force, extra_files=extra)
        cb("done", 1.0)
    for note in db.meta.get("import_notes", []):
        console.print(f"note: {note}", highlight=False, soft_wrap=True)
    n_rest = len(rest_pose_rows(db.scans, db.meta))
    said = ("each subject's first mesh (--rest-pose first)" if rule.get(REST_POSE_FIRST)
            else f"pose '{rule['pose']}'" + ("" if rest_pose is not None else " (the default; --rest-pose changes it)"))
    turned = f"; turned from {up} up to +Y" if up not in (None, "y") else ""
    out_console.print(f"wrote {out}: {db.n_scans} scans of {db.n_subjects} subjects, {db.n_vertices} vertices "
                      f"(read in {units}{turned}); rest pose: {said}, {n_rest} scans; labels: "
                      f"{', '.join(c for c in db.subjects if c != 'subject') or 'none'}", highlight=False, soft_wrap=True)
    if landmarks is not None:
        out_console.print(f"landmarks: {landmarks} measures the rest scans; stored as {out / LANDMARKS_FILE} "
                          "(bodyspace build uses it)", highlight=False, soft_wrap=True)
    if placed is not None:
        out_console.print(placed, highlight=False, soft_wrap=True)


def _place(db: ScanDatabase, landmarks: Path) -> str | None:
    """Stand ``db``'s meshes in our frame (facing +Z, on the floor over the origin: one rigid move
    for all, from the rest scans' landmarks; ``conventions.standing_placement``), in place; say
    what moved. A scanner's frame turned 140° showed every picture (lineups, crowds) from the
    back and put generated bodies metres away from the origin and under the floor."""
    rows = rest_pose_rows(db.scans, db.meta)[:16]
    found = standing_placement(load_landmarks(landmarks)[0], np.asarray(db.vertices[np.sort(rows)], dtype=float))
    if found is None:
        return (f"placement kept: {landmarks} has no shoulder and hip joints (shoulder_joint_l/r, hip_joint_l/r) to "
                "tell which way the bodies face")
    R, t, yaw = found
    vertices = np.asarray(db.vertices)
    if not vertices.flags.writeable:
        vertices = vertices.copy()
    for s in range(0, len(vertices), 256):       # in place, a chunk at a time: no float64 copy of all
        vertices[s:s + 256] = vertices[s:s + 256].astype(float) @ R.T + t
    db.vertices = vertices
    db.meta["provenance"]["placement"] = {"faced_degrees": round(yaw, 3), "moved_m": [round(float(x), 6) for x in t],
                                          "rule": "facing +Z, floor y = 0, hip joints over the origin"}
    return (f"placed: the bodies faced {yaw:+.0f}° from +Z about the vertical, stood {np.hypot(t[0], t[2]):.2f} m from "
            f"the origin with the floor at y = {-t[1]:.2f} m; turned to face +Z and moved onto the floor over the "
            "origin (from the rest scans' shoulder and hip joints; --keep-placement keeps the meshes as they are)")


def _import_scans(folder: Path, labels: Path, out: Path, *, rest_pose, units, up, landmarks, faces, model, steps,
                  force) -> None:
    """``import --register``: register each scan the labels CSV names, build the database of the
    accepted ones (``ScanDatabase.from_meshes`` on their registered meshes), list the refused."""
    if landmarks is not None:
        raise DatabaseError("--landmarks gives the landmarks of your own meshes' topology; with --register the "
                            "meshes are the template's (its landmarks are known) and each scan's own landmarks "
                            "are read from NAME.lnd or NAME.landmarks.json beside it")
    if faces is not None:
        raise DatabaseError("--faces is for NPY meshes of your own topology; with --register it is not used")
    if units is not None:
        units = check_choice(units, "--units", MESH_UNITS)
    if up is not None:
        up = check_choice(up, "--up", UP_ROTATIONS)
    check_folder_output(out, "--out", force, DATABASE_KIND)
    if not folder.is_dir():
        raise DatabaseError(f"{folder}: not a folder; expected a folder of raw scans")
    # The CSV before minutes of registration: its columns, and that every scan it names is there.
    cells, lines = read_csv_columns(labels)
    check_label_columns(cells, (MESH_COLUMN, SUBJECT_ID_COLUMN, "pose", SEX_COLUMN), str(labels))
    if MESH_COLUMN not in cells or not lines:
        raise DatabaseError(f"{labels}: expected a '{MESH_COLUMN}' column naming the scan files in {folder} and one "
                            f"row per scan; found columns {list(cells)} and {len(lines)} row(s)")
    names = cells[MESH_COLUMN]
    missing = [(n, line) for n, line in zip(names, lines) if not (folder / n).is_file()]
    if missing:
        listed = ", ".join(f"'{n}' (line {line})" for n, line in missing[:5])
        raise DatabaseError(f"{labels}: {len(missing)} scan(s) not found in {folder}: {listed}; expected file "
                            "names relative to the scan folder")
    template = load_template()
    basis, mset = registration_model(model, template)
    with progress("import --register", eta=True) as cb:
        outcomes = register_files([folder / n for n in names], template=template, units=units, up=up, basis=basis,
                                  mset=mset, steps=steps, progress=cb)
    # Each fit stands in the frame its own registration chose (the scan's turn about the vertical
    # kept, up to 25° on a T-posed scan; the floor where the scan had it, 0.83 m under y = 0 on a
    # scanner's Z-up millimetres): each is turned to face +Z and put on the floor over the origin,
    # as import does for registered meshes, so pictures, generated bodies and morphs stand alike.
    placement_set = load_measurement_set()
    turned = {}
    for i, o in enumerate(outcomes):
        if o.accepted:
            R, t, yaw = standing_placement(placement_set.landmarks, o.vertices[None])
            o.vertices = o.vertices @ R.T + t
            turned[i] = yaw
    for i, o in enumerate(outcomes):
        if o.accepted:
            console.print(f"{o.path.name}: registered in {o.seconds:.0f} s, {o.quality.describe()}"
                          f"{'' if o.landmarks is None else f'; landmarks {o.landmarks.name}'}; "
                          f"read in {o.units}, {o.up}{' axis' if up is None else ''} up; turned {-turned[i]:+.0f}° to face +Z",
                          markup=False, highlight=False, soft_wrap=True)
        else:
            console.print(f"{o.path.name}: REFUSED, left out: {o.reason}", markup=False, highlight=False,
                          soft_wrap=True)
        for note in o.notes:
            console.print(f"  [assumed] {note}", markup=False, highlight=False, soft_wrap=True)
    # One folder, one scanner: scans read in different units or up axes (each found on its own
    # when --units/--up are not given) are named, as one of them is likely misread.
    for what, given, flag in (("units", units, "--units"), ("up", up, "--up")):
        found = {}
        for o in outcomes:
            if getattr(o, what):
                found.setdefault(getattr(o, what), []).append(o.path.name)
        if given is None and len(found) > 1:
            listed = "; ".join(f"{k}: {', '.join(v[:5])}{' ...' if len(v) > 5 else ''}" for k, v in found.items())
            console.print(f"[warning] the scans were not all read in the same {'unit' if what == 'units' else 'up axis'}"
                          f" ({listed}); if they come from one scanner, give {flag} so that none is misread",
                          markup=False, highlight=False, soft_wrap=True)
    # Without a pose column every scan is the subject's rest scan (build --selection rest): fits
    # standing otherwise (a T-pose, elbows bent) would put their pose into the shape space.
    posed = [o for o in outcomes if o.accepted and o.pose_degrees > POSED_DEGREES]
    if "pose" not in cells and posed:
        listed = ", ".join(f"{o.path.name} ({o.pose_degrees:.0f}°)" for o in posed[:8])
        console.print(f"[warning] {labels} has no 'pose' column, so every scan counts as its subject's rest pose, but "
                      f"{len(posed)} fit(s) stand otherwise (a joint turned over {POSED_DEGREES:.0f}° from the rest "
                      f"A-pose): {listed}{' ...' if len(posed) > 8 else ''}; a model built with --selection rest "
                      "takes their poses into its shape space. Add a 'pose' column naming each subject's rest "
                      "scan 'rest' (and --rest-pose), or scan in the A-pose", markup=False, highlight=False,
                      soft_wrap=True)
    kept = [i for i, o in enumerate(outcomes) if o.accepted]
    if not kept:
        raise DatabaseError(f"{folder}: none of the {len(outcomes)} scans could be registered (each one's reason is "
                            "listed above); expected scans of one person standing alone")
    with tempfile.TemporaryDirectory(prefix="bodyspace-import-") as tmp:
        tmp = Path(tmp)
        np.save(tmp / "faces.npy", template.faces)
        table = {k: [v[i] for i in kept] for k, v in cells.items()}
        # The subject defaults to the scan's file stem: said explicitly, the meshes are renamed here.
        stems = [Path(names[i]).stem for i in kept]
        table[SUBJECT_ID_COLUMN] = [s or stem for s, stem in zip(table.get(SUBJECT_ID_COLUMN, [""] * len(kept)),
                                                                   stems)]
        table[MESH_COLUMN] = [f"{k}.npy" for k in range(len(kept))]
        for k, i in enumerate(kept):
            np.save(tmp / f"{k}.npy", outcomes[i].vertices.astype(np.float32))
        with open(tmp / labels.name, "w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(list(table))
            w.writerows(zip(*table.values()))
        try:
            db = ScanDatabase.from_meshes(tmp, tmp / labels.name, length_unit="m", rest_pose=rest_pose,
                                          faces=tmp / "faces.npy", spelling="cli")
        except DatabaseError as exc:
            raise DatabaseError(f"{labels} (the rows of the {len(kept)} registered scans): {exc}") from None
    db.meta[REST_POSE_FIELD] = choose_rest_pose(db.scans, rest_pose, str(labels))
    db.meta["provenance"].update({"source": "bodyspace import --register", "folder": str(folder),
                                  "labels": str(labels), "model": None if model is None else str(model),
                                  "placement": {"rule": "each fit turned to face +Z, floor y = 0, hip joints over "
                                                "the origin"}})
    db.meta["template"] = template.template_id
    report = io.StringIO()
    w = csv.writer(report)
    w.writerow(["scan", "accepted", "quality", "explained_share", "coverage_share", "weakest_part",
                "weakest_part_quality", "mean_distance_mm", "seconds", "landmarks", "units", "up", "turned_degrees", "pose_degrees",
                "assumed", "reason"])
    for i, o in enumerate(outcomes):
        q = o.quality
        weakest = None if q is None or not q.parts else min(q.parts, key=lambda p: p.quality)
        w.writerow([o.path.name, int(o.accepted), "" if q is None else f"{q.quality:.4f}",
                    "" if q is None else f"{q.explained:.4f}", "" if q is None else f"{q.coverage:.4f}",
                    "" if weakest is None else weakest.name, "" if weakest is None else f"{weakest.quality:.4f}",
                    "" if not np.isfinite(o.mean_distance) else f"{1000 * o.mean_distance:.3f}", f"{o.seconds:.1f}",
                    "" if o.landmarks is None else o.landmarks.name, o.units, o.up,
                    f"{-turned[i]:.1f}" if i in turned else "",
                    f"{o.pose_degrees:.1f}" if np.isfinite(o.pose_degrees) else "", " | ".join(o.notes), o.reason])
    db.save(out, overwrite=force, extra_files={REGISTRATION_REPORT: report.getvalue()})
    refused = [o for o in outcomes if not o.accepted]
    out_console.print(f"wrote {out}: {db.n_scans} registered scans of {db.n_subjects} subjects ({db.n_vertices} "
                      f"vertices, the template's topology); {len(refused)} refused and left out"
                      f"{': ' + ', '.join(o.path.name for o in refused) if refused else ''}; per-scan quality in "
                      f"{out / REGISTRATION_REPORT}", highlight=False, soft_wrap=True)
