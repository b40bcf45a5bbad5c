"""``bodyspace import``: a scan database from a user's own folder of registered meshes and a
labels CSV (``ScanDatabase.from_meshes``), without writing Python."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from bodyspace.cli.common import ForceOption, check_choice, check_folder_output, console, out_console, progress
from bodyspace.data.database import (
    DATABASE_KIND,
    LANDMARKS_FILE,
    REST_POSE_FIELD,
    REST_POSE_FIRST,
    UP_ROTATIONS,
    ScanDatabase,
    choose_rest_pose,
    rest_pose_rows,
)
from bodyspace.model import check_landmark_file

LENGTH_UNITS = ("m", "cm", "mm")


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
                  units: str = typer.Option("m", "--units", help="Length unit of the mesh coordinates: m, cm or mm "
                                                                 "(stored in metres)."),
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
                  force: bool = ForceOption):
    """Import a folder of your own registered meshes and a labels CSV as a scan database."""
    units = check_choice(units, "--units", LENGTH_UNITS)
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
        if landmarks is not None:
            cb(f"checking {landmarks} on the rest scans", 0.7)
            extra[LANDMARKS_FILE] = check_landmark_file(landmarks, db)
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
