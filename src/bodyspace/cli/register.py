"""``bodyspace register`` (a raw scan → the template fitted to it, measured) and ``bodyspace
landmarks`` (a mesh of any topology → a landmark file for ``measure --landmarks``)."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from bodyspace.atomic import write_json
from bodyspace.cli.common import (ForceOption, check_choice, check_file_output, check_folder_output, console,
                                  output_folder, progress)
from bodyspace.data.template import load_template
from bodyspace.errors import MeshError, RegistrationError
from bodyspace.measure import evaluate, load_measurement_set, to_json
from bodyspace.measure.conventions import MESH_UNITS, UP_AXES
from bodyspace.mesh.io import load_mesh, save_mesh
from bodyspace.register.detail import MAX_LEVELS, apply_detail, save_detail
from bodyspace.register.landmark_files import read_scan_landmarks
from bodyspace.register.landmarks import carry_vertex_data, landmark_document, mesh_joints, mesh_landmarks
from bodyspace.model import BodyModel
from bodyspace.register.pipeline import DEFAULT_STEPS, register_scan
from bodyspace.register.user_model import basis_from_model, check_model_topology
from bodyspace.register.prepare import read_scan
from bodyspace.report.registration import distance_figure
from bodyspace.report.render import contact_sheet
from bodyspace.rig.kinematics import matrix_to_rotvec
from bodyspace.rig.unpose import unpose

REGISTRATION_KIND = "registration"
UnitsOption = typer.Option(None, "--units", help="The scan's length unit: m, cm, mm or in. Default: found from its "
                           "size (printed).")
UpOption = typer.Option(None, "--up", help="The scan's up axis: y, -y, x, -x, z (Z up, facing -Y) or -z. Default: "
                        "the axis it spreads most along, which end is the head found by the fit (printed).")


def _read_landmarks(path: Path) -> dict:
    """--landmarks FILE (JSON or CAESAR .lnd, ``register.landmark_files``), notes printed."""
    lms, notes = read_scan_landmarks(path, flag="--landmarks")
    for note in notes:
        console.print(f"[landmarks] {note}", markup=False, highlight=False)
    return lms


def _standing_measurements(reg, template, mset=None) -> dict:
    """Measurements of the registered body standing (``Registration.standing``: the model refitted
    to the scan splits pose and shape, the fit's surface kept as normal offsets), with ``mset``
    (default the shipped set)."""
    mset = mset if mset is not None else load_measurement_set()
    if reg.standing is not None:
        rest = reg.standing
        nonroot = np.asarray(template.rigs["default"].parents) >= 0
        turned = np.degrees(np.linalg.norm(matrix_to_rotvec(reg.standing_pose.rotations[nonroot]), axis=-1)).max()
        note = ("measured standing: the shape model refitted to the scan, its rest body with the fit's surface as "
                f"normal offsets (largest joint turn undone {turned:.0f} degrees)")
    else:
        try:
            rest, _, info = unpose(reg.internal, template.rigs["default"], mesh_name="the registered mesh")
            note = f"measured standing: unposed first ({info.describe()})"
        except MeshError as exc:
            rest, note = reg.internal, f"measured as posed: the fit could not be unposed ({exc})"
    rows = to_json(evaluate(mset, rest, reg.faces, mesh_name="the registered mesh"))
    rows["unposed"] = {"value": None, "unit": "", "note": note}
    return rows


def register(scan: Path = typer.Argument(..., help="A raw scan: PLY/OBJ/STL/GLB point cloud or mesh, or XYZ/TXT/CSV/NPY "
                                          "points (any frame and unit: see --units, --up)."),
             out: Path = typer.Option(..., "--out", help="Output folder (refused if it exists, unless --force)."),
             landmarks: Optional[Path] = typer.Option(None, "--landmarks", help="JSON {\"landmarks\": {name: [x, y, z]}} "
                                                      "of measurement-set landmarks on the scan (its frame and "
                                                      "units; at least 3), or a CAESAR .lnd file: a similarity "
                                                      "alignment, weighted in."),
             model: Optional[Path] = typer.Option(None, "--model", help="A BodyModel file (bodyspace build) of the "
                                                  "template's topology: its shape space, mean body and measurement "
                                                  "set are used instead of the default ones."),
             units: Optional[str] = UnitsOption, up: Optional[str] = UpOption,
             steps: int = typer.Option(DEFAULT_STEPS, "--steps", min=1, max=40, help="Stiffness levels of the "
                                       "non-rigid refinement (3000 → 30)."),
             detail: bool = typer.Option(False, "--detail", help="Also keep the scan's fine relief (wrinkles, face) as "
                                         "normal offsets on the fit subdivided at mid-edges (Hasler §3): writes "
                                         "detail.npz (bodyspace morph --detail re-adds it) and the detailed mesh."),
             detail_levels: int = typer.Option(1, "--detail-levels", min=1, max=MAX_LEVELS, help="Mid-edge "
                                               "subdivisions for --detail: 1 (107 k faces, 3 mm edges) or 2 "
                                               "(428 k faces, 1.6 mm)."),
             no_check: bool = typer.Option(False, "--no-check", help="Write the fit even when its quality is below "
                                           "the threshold (it is refused by default)."),
             force: bool = ForceOption):
    """Fit the template to a raw scan: registered mesh, distances, pose, measurements, a PNG."""
    check_folder_output(out, "--out", force, REGISTRATION_KIND)      # before the fit, not after it
    if units is not None:
        units = check_choice(units, "--units", MESH_UNITS)
    if up is not None:
        up = check_choice(up, "--up", UP_AXES)
    template = load_template()
    basis, mset = registration_model(model, template)
    points, faces = read_scan(scan)
    lms = _read_landmarks(landmarks) if landmarks is not None else None
    with progress("register") as report:
        try:
            reg = register_scan(points, faces, template=template, units=units, up=up, landmarks=lms, steps=steps,
                                basis=basis, mset=mset,
                                check=not no_check, name=str(scan), progress=report,
                                detail_levels=detail_levels if detail else None)
        except RegistrationError as exc:
            raise RegistrationError(f"{exc}{'' if no_check or 'refused' not in str(exc) else ' (--no-check writes it anyway)'}") from None
    for line in reg.assumed:
        console.print(f"[assumed] {line}", markup=False, highlight=False)
    measurements = _standing_measurements(reg, template, mset)
    rig = template.rigs["default"]
    with output_folder(out, "--out", force, REGISTRATION_KIND) as tmp:
        save_mesh(tmp / "registered.obj", reg.vertices, reg.faces)
        save_mesh(tmp / "registered_standard.obj", reg.internal, reg.faces)
        if reg.standing is not None:
            save_mesh(tmp / "standing.obj", reg.standing, reg.faces)
        with open(tmp / "distance.csv", "w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(["vertex", "distance_mm"])
            w.writerows((i, f"{1000 * d:.3f}") for i, d in enumerate(reg.distance))
        write_json(tmp / "pose.json", {
            "written_by": "bodyspace", "rig": rig.name, "convention": "rotation vectors (radians) per bone, rest-pose "
            "world axes about the bone heads (pose_bodies); scale and translation (m) place the posed template",
            "rotations": {b: [round(float(c), 6) for c in r] for b, r in zip(rig.bone_names,
                                                                              matrix_to_rotvec(reg.pose.rotations))},
            "scale": reg.pose.scale, "translation_m": [float(c) for c in reg.pose.translation],
            "to_scan": reg.to_scan.tolist(), "shape_coefficients": [float(c) for c in reg.coefficients]})
        write_json(tmp / "measurements.json", {"written_by": "bodyspace", "measurements": measurements})
        with open(tmp / "measurements.csv", "w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(["name", "value", "unit", "note"])
            for name, e in measurements.items():
                w.writerow([name, "" if e["value"] is None else e["value"], e["unit"], e.get("note", "")])
        q = reg.quality
        write_json(tmp / "summary.json", {
            "written_by": "bodyspace", "scan": str(scan), "model": None if model is None else str(model),
            "shape_space": "the default (MakeHuman phenotype range)" if basis is None else
            f"{model}: {len(basis.sigma)} components", "units": reg.units, "up": reg.up, "assumed": reg.assumed,
            "quality": round(q.quality, 4), "explained_share": round(q.explained, 4),
            "coverage_share": round(q.coverage, 4), "accepted": reg.accepted, "quality_accepted": q.accepted,
            "one_sided": reg.one_sided, "failed_parts": q.to_dict()["failed_parts"],
            "parts": q.to_dict()["parts"], "restarted_limbs": reg.restarted,
            "mean_vertex_distance_mm": round(1000 * float(np.mean(reg.distance)), 3),
            "seconds": {k: round(v, 2) for k, v in reg.seconds.items()},
            **({} if reg.detail is None else {"detail": _detail_summary(reg.detail)})})
        with open(tmp / "quality.csv", "w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(["part", "quality", "accepted", "seen_share", "mean_distance_mm", "unexplained_cm2", "area_cm2",
                        "bridged_cm2"])
            for part, e in q.to_dict()["parts"].items():
                w.writerow([part, e["quality"], int(e["accepted"]), e["seen_share"], e["mean_distance_mm"],
                            e["unexplained_cm2"], e["area_cm2"], e["bridged_cm2"]])
        if reg.detail is not None:
            save_detail(tmp / "detail.npz", reg.detail, written_by="bodyspace register", scan=str(scan),
                        base_mesh="registered_standard.obj")
            dv, df = apply_detail(reg.internal, reg.faces, reg.detail, name="the registered mesh")
            save_mesh(tmp / "detailed_standard.obj", dv, df)
            save_mesh(tmp / "detailed.obj", dv @ reg.to_scan[:3, :3].T + reg.to_scan[:3, 3], df)
        distance_figure(reg.points[q.point_index], q.point_distance, tmp / "distance.png",
                        title=f"{scan.name}: scan points coloured by distance to the fit; {q.describe()}")
    console.print(f"{q.describe()}", markup=False, highlight=False)
    if reg.detail is not None:
        console.print(f"detail: {reg.detail.describe()}", markup=False, highlight=False)
    standing = "standing.obj (the body standing, measured), " if reg.standing is not None else ""
    console.print(f"wrote {out}/ (registered.obj in the scan's frame, registered_standard.obj in metres +Y up, "
                  f"{standing}distance.csv, pose.json, measurements.json/csv, summary.json, quality.csv (per body part), "
                  "distance.png"
                  f"{'; detail.npz, detailed.obj, detailed_standard.obj' if reg.detail is not None else ''})",
                  markup=False, highlight=False)


def _detail_summary(detail) -> dict:
    """summary.json's ``detail``: how much of the scan's relief was kept and why (``Detail``)."""
    def share(x):
        return None if not np.isfinite(x) else round(float(x), 4)
    return {"levels": detail.levels, "on_scan_share": round(float(detail.valid.mean()), 4),
            "kept_share": share(detail.kept), "too_sparse_share": share(detail.wide),
            "noise_mm": None if not np.isfinite(detail.noise) else round(1000 * detail.noise, 3),
            "offsets_rms_mm": round(1000 * float(np.sqrt(np.mean(detail.offsets ** 2))), 3), "notice": detail.notice()}


def landmarks(mesh: Path = typer.Argument(..., help="A body mesh of any topology (OBJ/PLY/GLB/STL; any frame and unit)."),
              out: Path = typer.Option(..., "--out", help="The landmark file to write (.json; refused if it exists, "
                                       "unless --force)."),
              png: Optional[Path] = typer.Option(None, "--png", help="Also draw the landmarks on the mesh to this PNG."),
              units: Optional[str] = UnitsOption, up: Optional[str] = UpOption,
              force: bool = ForceOption):
    """Landmarks for a mesh of another topology: register the template to it and carry them across."""
    check_file_output(out, "--out", force, (".json",), example="landmarks.json")
    if png is not None:
        check_file_output(png, "--png", force, (".png",), example="landmarks.png")
    if units is not None:
        units = check_choice(units, "--units", MESH_UNITS)
    if up is not None:
        up = check_choice(up, "--up", UP_AXES)
    vertices, faces = load_mesh(mesh)
    template = load_template()
    with progress("landmarks") as report:
        lms, reg = mesh_landmarks(vertices, faces, template=template, units=units, up=up, progress=report)
    for line in reg.assumed:        # units, up axis, a floor removed: what was found rather than given
        console.print(f"[assumed] {line}", markup=False, highlight=False)
    carried = carry_vertex_data(reg.vertices, template, vertices, faces)
    doc = landmark_document(lms, len(vertices), carried, mesh_joints(reg, template, vertices, faces),
                            written_by="bodyspace",
                            note=f"carried from the template registered to {mesh.name}: {reg.quality.describe()}; "
                                 "vertex_parts, skin_weights and joints are the template's body parts, skin weights "
                                 "and neck joints carried to this mesh")
    write_json(out, doc)
    if png is not None:
        to_internal = np.linalg.inv(reg.to_scan)
        v = vertices @ to_internal[:3, :3].T + to_internal[:3, 3]
        crosses = []
        for ids, w in lms.values():
            c = w @ v[ids]
            for axis in np.eye(3) * 0.015:
                crosses.append(np.stack([c - axis, c + axis]))
        contact_sheet([v], [faces], png, labels=[f"{mesh.name}: {len(lms)} landmarks"], views=("front", "side"),
                      polylines=[crosses], title="bodyspace landmarks", panel_height=6.0)
    console.print(f"{reg.quality.describe()}", markup=False, highlight=False)
    # The up axis the registration found (signed), so the suggested command runs as printed:
    # measure does not guess the up axis, it refuses a body that is not +Y up.
    up_found = up or scan_up_axis(reg.to_scan)
    console.print(f"wrote {out} ({len(lms)} landmarks, the neck joints, the body part and skin weights of each of "
                  f"the {len(vertices)} vertices; bodyspace measure {mesh} "
                  f"--landmarks {out} --units {units or reg.units}{'' if up_found == 'y' else f' --up {up_found}'})",
                  markup=False, highlight=False)


def scan_up_axis(to_scan: np.ndarray) -> str:
    """The scan frame's axis nearest the body's up direction ("y", "-z", ...), from the (4, 4)
    internal → scan transform of a registration."""
    up = to_scan[:3, :3] @ np.array([0.0, 1.0, 0.0])
    axis = int(np.argmax(np.abs(up)))
    return ("-" if up[axis] < 0 else "") + "xyz"[axis]


def registration_model(model: Path | None, template) -> tuple:
    """The shape basis and measurement set of ``--model MODEL`` (None, None without one): the
    model is checked to be of the template's topology, named by its flag in any refusal."""
    if model is None:
        return None, None
    user = BodyModel.load(model, semantics=False)
    check_model_topology(user, template, where=f"--model {model}")
    basis = basis_from_model(user, where=f"--model {model}")
    return basis, (user.measurement_set if user.has_measurement_set else None)
