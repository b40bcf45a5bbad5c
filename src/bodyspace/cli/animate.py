"""``bodyspace animate MODEL|MESH --motion CLIP.bvh --out walk.glb|walk.bvh|walk.npz|walk_%04d.ply|DIR``:
a motion capture clip on a body (Rupprecht §3.3.3).

The body is a model's (``--set stature=185cm ...`` through the semantic model, as ``generate``
does; without ``--set`` the model's mean body) or a mesh: of the template topology (the template
itself, a ``generate`` or ``sample`` output: the CC0 rig regressed on it, MakeHuman's weights), or
any closed humanoid mesh in an A- or T-pose (the rig embedded into it and bone-heat weights, as
``bodyspace rig`` does: ``cli.export.skeleton_and_weights``; the outputs are in metres, +Y up).
The clip is matched to the rig by structure (``motion.matching``), retargeted
(``motion.retarget``), its feet locked where the source's are planted (``motion.ik``; ``--no-ik``
leaves them), skinned (LBS with the rig's weights), and written as a rigged glTF with the
animation, a BVH of the clip on the body's skeleton, an ``.npz`` of the posed meshes, or one mesh
file a frame (``walk_%04d.ply`` or ``.obj``; a name without suffix: a folder of
``frame_0000.ply``, ...). A table
says what the clip does to the body: foot skating and floor penetration against the source,
before and after the foot locking, and arms through the torso.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import List, Optional

import numpy as np
import typer
from rich.table import Table

from bodyspace.atomic import WRITTEN_BY, write_json
from bodyspace.cli.common import (
    ForceOption,
    SeedOption,
    check_file_output,
    check_folder_output,
    console,
    out_console,
    output_folder,
    progress,
)
from bodyspace.cli.export import skeleton_and_weights
from bodyspace.cli.motion import BvhUnitOption
from bodyspace.cli.semantics import ClampOption, DatabaseOption, RefitOption, SetOption, load_semantics, parse_targets
from bodyspace.data.template import RIG_NAMES, load_template
from bodyspace.errors import MotionError, ParameterError
from bodyspace.export.gltf import SkeletonAnimation, write_gltf
from bodyspace.export.sequence import (
    NUMBERED_SUFFIXES,
    numbered_mesh_paths,
    write_mesh_sequence,
    write_numbered_meshes,
)
from bodyspace.mesh.io import load_mesh
from bodyspace.model import BodyModel
from bodyspace.motion.bvh import Motion, read_bvh, write_bvh
from bodyspace.motion.contacts import penetration, skating
from bodyspace.motion.ik import foot_vertices, knee_angles, lock_feet, sole_points
from bodyspace.motion.intersection import arm_torso_intersections, arm_torso_regions
from bodyspace.motion.matching import graph_from_motion, graph_from_skeleton, load_joint_map, match_skeletons
from bodyspace.motion.retarget import retarget, to_bvh
from bodyspace.report.animation import animated_gif, filmstrip
from bodyspace.rig.kinematics import linear_blend_skinning
from bodyspace.rig.scan_body import scan_body
from bodyspace.rig.volume import preserve_volume as correct_volume
from bodyspace.rig.volume import volume_rig

OUT_SUFFIXES = (".glb", ".bvh", ".npz")
# A folder --out (a name without suffix) holds one PLY a frame under this pattern.
FOLDER_FRAME_PATTERN = "frame_%04d.ply"
FOLDER_KIND = "animate mesh sequence"
_FILMSTRIP_PANELS = 8
_GIF_MAX_FRAMES = 60


def parse_frames(text: Optional[str], n_frames: int) -> slice:
    """``--frames START:STOP[:STEP]`` (0-based, STOP exclusive, like Python) as a slice."""
    if text is None:
        return slice(0, n_frames, 1)
    parts = text.split(":")
    usage = ParameterError(f"--frames {text!r}: expected START:STOP or START:STOP:STEP (frame numbers from 0), "
                           "e.g. 0:240 or 0:240:4")
    if len(parts) not in (2, 3) or not all(p.strip().lstrip("-").isdigit() or not p.strip() for p in parts):
        raise usage
    start = int(parts[0]) if parts[0].strip() else 0
    stop = int(parts[1]) if parts[1].strip() else n_frames
    step = int(parts[2]) if len(parts) == 3 and parts[2].strip() else 1
    if step < 1 or not 0 <= start < stop:
        raise ParameterError(f"--frames {text!r}: expected 0 <= START < STOP and STEP >= 1")
    if start >= n_frames:
        raise ParameterError(f"--frames {text!r}: the clip has {n_frames} frames (0 to {n_frames - 1})")
    return slice(start, min(stop, n_frames), step)


def _body(body: Path, sets, database, refit, clamp, seed) -> tuple[np.ndarray, np.ndarray, str]:
    """Rest vertices, faces and a description of the body to animate."""
    if body.suffix.lower() == ".npz":
        if sets:
            sm = load_semantics(body, database, refit, clamp)
            result = sm.body_model.generate(parse_targets(sets, None, allow_delta=False, sm=sm), rng=seed)
            asked = ", ".join(sets)
            return result.vertices, sm.body_model.faces, f"{body.name} generated for {asked}"
        model = BodyModel.load(body, semantics=False)
        return model.mean_vertices, model.faces, f"{body.name}: the model's mean body"
    if sets:
        raise ParameterError(f"--set asks a model for a body; {body} is a mesh. Pass the model file (.npz) instead, "
                             "or leave --set out to animate the mesh as it is")
    v, f = load_mesh(body)
    return v, f, f"{body.name}"


def _skeleton(vertices, faces, rig_name: str, where: str):
    """``(vertices, faces, skeleton, weights, how)``: the template's rig and weights on a body of
    its topology (in metres, +Y up, checked), else the rig embedded into the mesh with bone-heat
    weights (``skeleton_and_weights``: the vertices come back in metres, +Y up). A scanner's
    floor, turntable or pole is left out first, as ``bodyspace rig`` leaves it out
    (``rig.scan_body``; the body alone is animated, ``how`` says what was left out)."""
    template = load_template()
    if vertices.shape == template.vertices.shape and np.array_equal(faces, template.faces):
        size = float(np.ptp(vertices[:, 1]))
        if not 0.5 < size < 2.8:
            raise ParameterError(f"{where}: the body is {size:g} units tall; expected metres with +Y up (a body 0.5 "
                                 "to 2.8 m tall): scale it (centimetres x 0.01) and turn it first")
        left_out = ""
    else:
        found = scan_body(vertices, faces)
        left_out = "" if found is None else f"; left out: {'; '.join(found.notes)}"
        if found is not None:
            vertices, faces = vertices[found.vertex_ids], found.faces
    vertices, skeleton, weights, how = skeleton_and_weights(vertices, faces, rig_name, where)
    return vertices, faces, skeleton, weights, how + left_out


def _facing_front(posed: np.ndarray, root_rotations: np.ndarray) -> np.ndarray:
    """Frames (N, V, 3) turned about the vertical through each frame's centre so that the root
    bone's front (its rest +Z) faces +Z: previews show the body's front and side, wherever the
    clip walks. root_rotations: (N, 3, 3) world rotations of the root bone."""
    front = root_rotations[:, :, 2]
    angle = np.arctan2(front[:, 0], front[:, 2])                     # heading about +Y
    c, s = np.cos(-angle), np.sin(-angle)
    R = np.zeros((len(angle), 3, 3))
    R[:, 0, 0], R[:, 0, 2], R[:, 1, 1], R[:, 2, 0], R[:, 2, 2] = c, s, 1.0, -s, c
    centre = posed.mean(axis=1, keepdims=True)
    return (posed - centre) @ np.swapaxes(R, 1, 2) + centre


def _summary_table(rows: list[tuple[str, str, str, str]]) -> Table:
    table = Table(title="feet and arms (source contacts: height < 5 cm over the planted height, speed < 0.5 m/s)")
    for col in ("measure", "source clip", "retargeted", "with foot IK"):
        table.add_column(col, justify="left" if col == "measure" else "right")
    for r in rows:
        table.add_row(*r)
    return table


def animate(body: Path = typer.Argument(..., help="A model file (.npz, bodyspace build; a body is generated with "
                                                  "--set), a body mesh of the template topology (.obj, .ply, "
                                                  ".glb; metres, +Y up), or any closed humanoid mesh in an A- or "
                                                  "T-pose (rigged by embedding, as bodyspace rig)."),
            motion: Path = typer.Option(..., "--motion", help="The motion capture clip (.bvh)."),
            out: Path = typer.Option(..., "--out", help="walk.glb (rigged glTF with the animation), walk.bvh (the clip "
                                                        "on the body's skeleton), walk.npz (posed meshes, "
                                                        "frames x V x 3, metres), walk_%04d.ply or .obj (one mesh "
                                                        "a frame, numbered from 0) or a folder name without "
                                                        "suffix (frame_0000.ply, ... inside)."),
            sets: Optional[List[str]] = SetOption,
            rig_name: str = typer.Option("default", "--rig", help="The CC0 rig: " + ", ".join(RIG_NAMES) + "."),
            frames: Optional[str] = typer.Option(None, "--frames", help="Frames of the clip to use, START:STOP[:STEP] "
                                                                        "from 0, e.g. 0:240:4 (default: all)."),
            no_ik: bool = typer.Option(False, "--no-ik", help="Leave the feet as retargeted (no foot locking)."),
            keep_volume: bool = typer.Option(False, "--preserve-volume",
                                             help="Keep every frame's enclosed volume equal to the rest body's "
                                                  "(a smooth bulge around bent joints on top of LBS; docs/skinning.md). "
                                                  "For mesh outputs (.npz, numbered meshes, a folder) and the "
                                                  "previews; a .glb or .bvh cannot carry it."),
            filmstrip_png: Optional[Path] = typer.Option(None, "--filmstrip", help="A PNG of every n-th frame "
                                                                                  "(--every), front and side."),
            every: Optional[int] = typer.Option(None, "--every", min=1, help="Frames between filmstrip panels "
                                                                             "(default: 8 panels over the clip)."),
            gif: Optional[Path] = typer.Option(None, "--gif", help="An animated GIF (side view, at most 60 frames "
                                                                   "spread over the clip)."),
            report: Optional[Path] = typer.Option(None, "--report", help="The table as JSON (skating, penetration, "
                                                                         "intersections; metres, seconds)."),
            joint_map: Optional[Path] = typer.Option(None, "--map", help="JSON {\"clip joint\": \"rig bone\" or null} "
                                                                         "overriding the structural match."),
            bvh_unit: str = BvhUnitOption,
            seed: int = SeedOption("Random seed for what --set does not ask (an integer >= 0)."),
            clamp: bool = ClampOption, database: Optional[Path] = DatabaseOption, refit: bool = RefitOption,
            force: bool = ForceOption) -> None:
    """Put a motion capture clip on a body: retargeted (Rupprecht §3.3.3), feet kept still where the clip's feet are
    planted (two-bone IK), skinned; written as an animated rigged glTF, a BVH or a mesh sequence."""
    numbered = "%" in out.name
    folder = not numbered and out.suffix == ""
    if folder:
        check_folder_output(out, "--out", force, FOLDER_KIND)
    elif not numbered:
        check_file_output(out, "--out", force, OUT_SUFFIXES + NUMBERED_SUFFIXES, example="walk.glb")
        if out.suffix.lower() in NUMBERED_SUFFIXES:
            raise ParameterError(f"--out {out}: one mesh a frame needs a frame field in the name, e.g. --out "
                                 f"{out.with_name(out.stem + '_%04d' + out.suffix)}; or one file: "
                                 f"{', '.join(OUT_SUFFIXES)}")
    for flag, path, suffix in (("--filmstrip", filmstrip_png, ".png"), ("--gif", gif, ".gif"),
                               ("--report", report, ".json")):
        if path is not None:
            check_file_output(path, flag, force, (suffix,), example=f"walk{suffix}")
    if rig_name not in RIG_NAMES:
        raise ParameterError(f"--rig {rig_name!r}: not a rig of the template; expected one of {', '.join(RIG_NAMES)}")
    if keep_volume and not (numbered or folder) and out.suffix.lower() in (".glb", ".bvh"):
        raise ParameterError(f"--preserve-volume changes the posed meshes, which {out.suffix.lower()} does not store "
                             "(a viewer skins the .glb with plain LBS; a .bvh holds the skeleton only): write the "
                             "frames as walk.npz, walk_%04d.ply or a folder, or leave --preserve-volume out")
    if every is not None and filmstrip_png is None:
        raise ParameterError("--every spaces the --filmstrip panels; pass --filmstrip FILE.png too")
    clip = read_bvh(motion, unit=bvh_unit)
    if clip.n_frames == 0:
        raise MotionError(f"{motion}: holds no frames (Frames: 0); expected a clip")
    chosen = parse_frames(frames, clip.n_frames)
    original_dt = clip.frame_time
    clip = clip.frames(chosen)
    frame_files = numbered_mesh_paths(out, clip.n_frames) if numbered else None
    for path in frame_files or ():
        check_file_output(path, "--out", force, NUMBERED_SUFFIXES, example="walk_0000.ply")
    if chosen.step > 1:             # every STEP-th frame: the time between kept frames grows
        clip = Motion(clip.skeleton, clip.values, clip.frame_time * chosen.step, clip.unit, clip.unit_note,
                      clip.translation, clip.name)
    started = time.perf_counter()
    with progress(f"animating {motion.name}") as bar:
        bar("the body", 0.02)
        vertices, faces, said_body = _body(body, sets, database, refit, clamp, seed)
        vertices, faces, skeleton, weights, how = _skeleton(vertices, faces, rig_name, str(body))
        if how != "template topology":
            said_body = f"{said_body} ({how})"
        bar("matching the skeletons", 0.15)
        source_graph = graph_from_motion(clip)
        target_graph = graph_from_skeleton(skeleton)
        overrides = load_joint_map(joint_map, source_graph, target_graph) if joint_map is not None else None
        match = match_skeletons(source_graph, target_graph, overrides)
        bar("retargeting", 0.25)
        floor = float(vertices[:, 1].min())
        retargeted = retarget(clip, skeleton, match, target_floor=floor)
        final = retargeted
        if not no_ik:
            bar("locking the feet", 0.4)
            final, _ = lock_feet(retargeted, sole=sole_points(retargeted, weights, vertices))
        bar("skinning", 0.5)
        posed_before = linear_blend_skinning(vertices, weights, retargeted.transforms(), dtype=np.float32)
        posed = posed_before if no_ik else linear_blend_skinning(vertices, weights, final.transforms(),
                                                                 dtype=np.float32)
        if keep_volume:
            bar("keeping the volume", 0.55)
            vrig = volume_rig(weights, skeleton.parents, faces)
            corrected = [(posed_before, retargeted)] + ([] if no_ik else [(posed, final)])
            for frames_posed, clip_posed in corrected:
                correct_volume(frames_posed, vertices[None], clip_posed.transforms(), skeleton.heads[None],
                               skeleton.tails[None], vrig)
        bar("arms and torso", 0.6)
        arm, torso = arm_torso_regions(skeleton, weights, match.target_landmarks, vertices)
        crossing = arm_torso_intersections(posed, faces, arm, torso,
                                           progress=lambda m, f: bar(f"arms and torso: {m}", 0.6 + 0.15 * f))
        bar("writing", 0.75)
        transforms = final.transforms()
        suffix = out.suffix.lower()
        extras = {"clip": motion.name, "body": said_body, "rig": rig_name, "frames": clip.n_frames,
                  "frame_time_s": clip.frame_time, "leg_ratio": retargeted.leg_ratio, "foot_ik": not no_ik}
        if suffix == ".glb":
            write_gltf(out, vertices, faces, skeleton, weights, extras={"rig": rig_name, "motion": extras},
                       animation=SkeletonAnimation(transforms, clip.frame_time, name=clip.name))
        elif suffix == ".bvh":
            write_bvh(out, to_bvh(final))
        elif numbered:
            write_numbered_meshes(frame_files, posed, faces)
        elif folder:
            with output_folder(out, "--out", force, FOLDER_KIND) as tmp:
                write_numbered_meshes(numbered_mesh_paths(tmp / FOLDER_FRAME_PATTERN, clip.n_frames), posed, faces)
        else:
            write_mesh_sequence(out, posed, faces, clip.frame_time, extras={"motion": extras})
        root = int(np.flatnonzero(skeleton.parents < 0)[0])
        if filmstrip_png is not None:
            n = clip.n_frames
            step = every or max(1, int(np.ceil(n / _FILMSTRIP_PANELS)))
            pick = np.arange(0, n, step)
            bar("filmstrip", 0.8)
            frames_shown = _facing_front(posed[pick].astype(float), transforms[pick, root, :3, :3])
            filmstrip(filmstrip_png, frames_shown, faces,
                      [f"frame {k} ({k * original_dt:.2f} s)" for k in chosen.start + pick * chosen.step],
                      title=f"{clip.name} on {said_body}, rig {rig_name} (each frame turned to face the camera)",
                      ncols=min(len(pick), 4))
        if gif is not None:
            step = max(1, int(np.ceil(clip.n_frames / _GIF_MAX_FRAMES)))
            pick = np.arange(0, clip.n_frames, step)
            # one turn for the whole clip: the body's first heading faces the camera's side view
            turned = _facing_front(posed[pick].astype(float), np.broadcast_to(transforms[0, root, :3, :3],
                                                                              (len(pick), 3, 3)))
            animated_gif(gif, turned, faces, clip.frame_time * step, title=f"{clip.name}",
                         progress=lambda m, f: bar(f"GIF: {m}", 0.85 + 0.14 * f))
        bar("done", 1.0)
    # what the clip does to this body
    fb, ff = retargeted.feet(), final.feet()
    src = skating(fb.source, fb.contacts, clip.frame_time)
    before = skating(fb.target, fb.contacts, clip.frame_time)
    after = skating(ff.target, ff.contacts, clip.frame_time)
    pen_src = penetration(fb.source[..., 1] - np.percentile(fb.source[..., 1], 5, axis=0))
    feet_v = foot_vertices(retargeted, weights)
    rest_v = np.setdiff1d(np.arange(len(vertices)), feet_v)
    soles = [penetration(p[:, feet_v, 1]) for p in (posed_before, posed)]
    others = [penetration(p[:, rest_v, 1]) for p in (posed_before, posed)]
    knees = [np.degrees(np.abs(np.diff(knee_angles(c, source=s), axis=0))).max() / clip.frame_time
             if clip.n_frames > 1 else 0.0 for c, s in ((retargeted, True), (retargeted, False), (final, False))]
    ik = (lambda text: text if not no_ik else "-")
    rows = [("contact frames sliding > 2.5 cm", f"{src.share:.1%}", f"{before.share:.1%}", ik(f"{after.share:.1%}")),
            ("mean speed in contact", f"{src.mean_speed * 100:.1f} cm/s", f"{before.mean_speed * 100:.1f} cm/s",
             ik(f"{after.mean_speed * 100:.1f} cm/s")),
            ("foot joints below the floor (max)", f"{pen_src * 100:.1f} cm",
             f"{penetration(fb.target[..., 1] - fb.clearance) * 100:.1f} cm",
             ik(f"{penetration(ff.target[..., 1] - ff.clearance) * 100:.1f} cm")),
            ("feet's skin below the floor (max)", "", f"{soles[0] * 100:.1f} cm", ik(f"{soles[1] * 100:.1f} cm")),
            ("other skin below the floor (max)", "", f"{others[0] * 100:.1f} cm", ik(f"{others[1] * 100:.1f} cm")),
            ("fastest knee", f"{knees[0]:.0f} deg/s", f"{knees[1]:.0f} deg/s", ik(f"{knees[2]:.0f} deg/s")),
            ("arms in the torso > 5 mm", "", "", f"{crossing.frames} of {clip.n_frames} frames, deepest "
                                                 f"{crossing.max_depth * 100:.1f} cm (frame {crossing.worst_frame})")]
    out_console.print(_summary_table(rows))
    if report is not None:
        write_json(report, {"written_by": WRITTEN_BY, **extras, "body_stature_m": float(np.ptp(vertices[:, 1])),
                            "source": {"skating": src.to_dict(), "foot_joint_penetration_m": pen_src,
                                       "fastest_knee_deg_per_s": knees[0]},
                            "retargeted": {"skating": before.to_dict(), "feet_skin_penetration_m": soles[0],
                                           "other_skin_penetration_m": others[0], "fastest_knee_deg_per_s": knees[1]},
                            "foot_ik": None if no_ik else {"skating": after.to_dict(),
                                                           "feet_skin_penetration_m": soles[1],
                                                           "other_skin_penetration_m": others[1],
                                                           "fastest_knee_deg_per_s": knees[2]},
                            "arm_torso_intersections": crossing.to_dict()})
    said_out = f"{frame_files[0]} ... {frame_files[-1].name}" if numbered else out
    written = ", ".join(str(p) for p in (said_out, filmstrip_png, gif, report) if p is not None)
    console.print(f"wrote {written}: {clip.name} ({clip.n_frames} frames, {clip.duration:.2f} s) on {said_body}, rig "
                  f"{rig_name} ({skeleton.n_bones} bones), leg ratio {retargeted.leg_ratio:.3f}; "
                  f"{time.perf_counter() - started:.1f} s", highlight=False)
