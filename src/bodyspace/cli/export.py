"""Rigged glTF from the command line: ``bodyspace rig MESH --out body.glb`` and the ``--rig``
branch of ``bodyspace generate`` (``write_rigged``), with ``--morphs`` and ``--png``.

A body of the template topology carries a CC0 rig: its skeleton is regressed from the body's
own vertices (``rig.skeleton.body_skeleton``) and MakeHuman's skin weights apply as they are.
Any other mesh (another topology, frame or unit) gets the rig by skeleton embedding
(``rig.embed``: the template fitted into it) and bone-heat weights on its own surface
(``rig.weights.bone_heat_weights``); it is written in metres, +Y up, facing +Z (glTF's axes),
standing on y = 0. Both branches meet in ``skeleton_and_weights``.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from bodyspace.cli.common import ForceOption, check_file_output, console, fail
from bodyspace.data.template import RIG_NAMES, load_template
from bodyspace.errors import BodyspaceError, ParameterError
from bodyspace.export.gltf import write_gltf
from bodyspace.export.morphs import parse_morph_specs, semantic_morph_targets
from bodyspace.measure.conventions import MESH_UNITS, winding_inwards
from bodyspace.mesh.io import load_mesh
from bodyspace.model import BodyModel
from bodyspace.report.rig_figure import rig_figure
from bodyspace.rig.carried_weights import load_carried_weights
from bodyspace.rig.embed import embed_skeleton, embedded_skeleton
from bodyspace.rig.scan_body import scan_body
from bodyspace.rig.skeleton import body_skeleton
from bodyspace.rig.weights import bone_heat_weights

UP_CHOICES = ("y", "-y", "x", "-x", "z", "-z")
RigOption = typer.Option(None, "--rig", help="Write a rigged glTF (--out NAME.glb) with this CC0 rig: "
                                             + ", ".join(RIG_NAMES) + ".")
MorphsOption = typer.Option(None, "--morphs", help="With --rig: morph targets (shape keys) of the model's semantic "
                                                   "variables, NAME[=CHANGE] separated by commas, e.g. "
                                                   "stature,mass=+5kg,waist_girth (bare names: stature +10 cm, other "
                                                   "lengths +5 cm, mass +10 kg, age +10 years, body_fat +5 %, muscle "
                                                   "+0.25), each the true `bodyspace morph` of that change.")
PngOption = typer.Option(None, "--png", help="With --rig: a PNG of the skeleton over the body (front, side) and "
                                             "weight maps of --bones.")
BonesOption = typer.Option(None, "--bones", help="Bones for the --png weight maps, separated by commas (default: an "
                                                 "upper arm, the spine, a thigh, the head).")


def check_rig_options(out: Path, rig: Optional[str], morphs: Optional[str], png: Optional[Path],
                      bones: Optional[str], force: bool) -> None:
    """Refuse, before any work, rig options that cannot be met (naming the flag)."""
    if rig is None:
        for flag, value in (("--morphs", morphs), ("--png", png), ("--bones", bones)):
            if value is not None:
                raise ParameterError(f"{flag} needs --rig NAME (a rigged glTF); e.g. --rig default")
        return
    if rig not in RIG_NAMES:
        raise ParameterError(f"--rig {rig!r}: not a rig of the template; expected one of {', '.join(RIG_NAMES)}")
    if Path(out).suffix.lower() != ".glb":
        raise ParameterError(f"--out {out}: --rig writes a rigged binary glTF; expected a name ending in .glb")
    if morphs is not None:
        parse_morph_specs(morphs)
    if png is not None:
        check_file_output(png, "--png", force, (".png",), example="rig.png")
    if bones is not None and png is None:
        raise ParameterError("--bones chooses the weight maps of --png; pass --png FILE.png too")


def skeleton_and_weights(vertices: np.ndarray, faces: np.ndarray, rig_name: str, where: str, *,
                         up: Optional[str] = None, units: Optional[str] = None, weights_file: Optional[Path] = None,
                         source_vertices: Optional[tuple[int, np.ndarray]] = None):
    """``(vertices, skeleton, weights, how)`` of a body for rig ``rig_name``: the template's rig and
    MakeHuman's weights when the body has the template topology (vertices as given); else the
    rig embedded into the mesh and bone-heat weights, the vertices in metres, our axes (``up``,
    ``units``: the mesh's, found from it when None). ``how`` says which, for people.
    weights_file: a ``bodyspace landmarks`` file whose carried skin weights replace bone heat.
    source_vertices: (V0, ids (V,)) when the body is part of a mesh of V0 vertices the file is for
    (``rig.scan_body``: its floor left out): the body's vertex i is the file's ``ids[i]``."""
    template = load_template()
    v, f = np.asarray(vertices, dtype=float), np.asarray(faces)
    rig = template.rigs.get(rig_name)
    if rig is None:
        raise ParameterError(f"--rig {rig_name!r}: the asset folder has no such rig; it has "
                             f"{', '.join(template.rigs)}")
    inwards, ratio = winding_inwards(v, f)
    if inwards:
        # A glTF viewer culls back faces: a body wound inwards would be drawn inside out (a rig
        # of one was written without a word).
        raise ParameterError(f"{where}: its faces are wound inwards (signed volume / area^1.5 = {ratio:.3f}, expected "
                             "positive): a viewer would draw the body inside out; reverse them (bodyspace rig "
                             "--flip-winding, or save the mesh with its faces reversed)")
    if v.shape == template.vertices.shape and np.array_equal(f, template.faces) and up is None and units is None:
        if weights_file is not None:
            raise ParameterError(f"--weights {weights_file}: {where} has the template's topology, whose own skin "
                                 "weights are used; --weights is for meshes of another topology")
        return v, body_skeleton(rig, v, rest_vertices=template.vertices), rig.weights, "template topology"
    embedding = embed_skeleton(v, f, up=up, units=units, mesh_name=where)
    skeleton = embedded_skeleton(embedding, rig)
    body = embedding.frame.to_internal(v)
    how = (f"skeleton embedded (mesh up {embedding.frame.up}, {embedding.frame.units}; fit residual "
           f"{1000 * embedding.residual_m:.1f} mm), ")
    if weights_file is not None:
        # MakeHuman's weights carried by the registration (bodyspace landmarks): no bone heat.
        if source_vertices is None:
            carried = load_carried_weights(weights_file, len(v), rig)
        else:
            carried = load_carried_weights(weights_file, source_vertices[0], rig)[source_vertices[1]]
        return body, skeleton, carried, how + f"skin weights of {weights_file}"
    deform = np.asarray(abs(rig.weights).sum(axis=0)).ravel() > 0     # the bones MakeHuman's weights move
    weights = bone_heat_weights(body, f, skeleton.heads, skeleton.tails, deform=deform)
    how += "bone-heat weights"
    return body, skeleton, weights, how


def _linear_part(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """(3, 3) M with ``after - mean = (before - mean) @ M`` for a similarity (scale, rotation)
    between two (V, 3) copies of one mesh: how displacements of ``before`` map onto ``after``."""
    a, b = before - before.mean(axis=0), after - after.mean(axis=0)
    return np.linalg.lstsq(a, b, rcond=None)[0]


def write_rigged(out: Path, vertices: np.ndarray, faces: np.ndarray, rig_name: str, *, body_model=None,
                 morphs: Optional[str] = None, png: Optional[Path] = None, bones: Optional[str] = None,
                 where: str = "the body", up: Optional[str] = None, units: Optional[str] = None,
                 weights_file: Optional[Path] = None, source_vertices: Optional[tuple[int, np.ndarray]] = None) -> str:
    """Write the rigged ``.glb`` (and the ``--png``); returns a line saying what was written.
    source_vertices: as in ``skeleton_and_weights``; the ids are stored in the asset's extras
    (``source_vertices``) so the glTF's vertices can be traced back to the mesh's."""
    names = [b.strip() for b in bones.split(",")] if bones else None
    if morphs is not None and body_model is None:
        raise ParameterError("--morphs needs the model whose semantic variables they are; pass --model MODEL.npz")
    given = np.asarray(vertices, dtype=float)
    vertices, skeleton, weights, how = skeleton_and_weights(vertices, faces, rig_name, where, up=up, units=units,
                                                            weights_file=weights_file, source_vertices=source_vertices)
    for b in names or []:
        if b not in skeleton.bone_names:
            raise ParameterError(f"--bones {b!r}: not a bone of rig {rig_name}; expected names such as "
                                 f"{', '.join(skeleton.bone_names[:8])}, ... ({skeleton.n_bones} bones)")
    targets = []
    if morphs is not None:
        if given.shape != np.shape(body_model.template_vertices) or not np.array_equal(faces, body_model.faces):
            raise ParameterError(f"--morphs: {where} has {len(given)} vertices and other faces than the model "
                                 f"({len(body_model.template_vertices)} vertices); morph targets are made for bodies "
                                 "of the model's own topology (leave --morphs out, or give the model of this mesh)")
        targets = semantic_morph_targets(body_model, given, parse_morph_specs(morphs))
        if how != "template topology":
            # A body of the model's own (not the template's) topology is rigged by embedding, which
            # writes it in metres, +Y up, facing +Z: the same rigid move and scale carries the keys.
            targets = [replace(t, deltas=t.deltas @ _linear_part(given, vertices)) for t in targets]
    extras = {"rig": rig_name, "template": load_template().template_id}
    if source_vertices is not None:
        extras["source_vertices"] = {"count": int(source_vertices[0]), "ids": source_vertices[1].tolist()}
    write_gltf(out, vertices, faces, skeleton, weights, targets, extras=extras)
    said = f"wrote {out}: rig {rig_name} ({skeleton.n_bones} bones), {len(vertices)} vertices, {how}"
    if targets:
        said += ", morph targets " + ", ".join(t.name for t in targets)
    if png is not None:
        rig_figure(png, vertices, faces, skeleton, weights, bones=names,
                   title=f"{Path(out).name}: rig {rig_name}")
        said += f"; {png}"
    return said


def rig(mesh: Path = typer.Argument(..., help="A body mesh (.obj, .ply, .glb or .stl): of the template topology "
                                              "(from bodyspace generate or sample), or any closed humanoid mesh "
                                              "standing in an A- or T-pose (any vertex count, unit and up axis); "
                                              "a scan's floor, turntable or pole is left out, and said."),
        out: Path = typer.Option(..., "--out", help="The rigged binary glTF to write (.glb)."),
        rig_name: str = typer.Option("default", "--rig", help="The CC0 rig: " + ", ".join(RIG_NAMES) + "."),
        model: Optional[Path] = typer.Option(None, "--model", help="With --morphs: the model file (with semantic "
                                                                   "regressors) whose variables they are."),
        morphs: Optional[str] = MorphsOption, png: Optional[Path] = PngOption, bones: Optional[str] = BonesOption,
        up: Optional[str] = typer.Option(None, "--up", help="The mesh's up axis (y, -y, x, -x, z, -z); found from "
                                                            "the mesh when left out."),
        units: Optional[str] = typer.Option(None, "--units", help="The mesh's length unit (m, cm, mm, in); found "
                                                                  "from its size when left out."),
        weights: Optional[Path] = typer.Option(None, "--weights", help="Another topology: the landmark file of "
                                               "bodyspace landmarks MESH, whose carried MakeHuman skin weights are "
                                               "used instead of bone heat; its landmarks say which pieces of the "
                                               "mesh are the body."),
        flip_winding: bool = typer.Option(False, "--flip-winding", help="Reverse every face: for a mesh whose "
                                          "faces are wound inwards (refused otherwise: viewers would draw it inside "
                                          "out)."),
        force: bool = ForceOption):
    """A rigged glTF 2.0 of a body, bind pose = the mesh as given. Template topology: skeleton regressed from its
    vertices, MakeHuman's CC0 skin weights, optional morph targets of a model's semantic variables. Any other
    humanoid mesh: the rig embedded into it (the template fitted inside), bone-heat weights (4 per vertex), written
    in metres, +Y up, facing +Z."""
    check_file_output(out, "--out", force, (".glb",), example="body.glb")
    try:
        check_rig_options(out, rig_name, morphs, png, bones, force)
        if up is not None and up not in UP_CHOICES:
            raise ParameterError(f"--up {up!r}: expected one of {', '.join(UP_CHOICES)}")
        if units is not None and units not in MESH_UNITS:
            raise ParameterError(f"--units {units!r}: expected one of {', '.join(MESH_UNITS)}")
        if model is not None and morphs is None:
            raise ParameterError("--model is read for --morphs only; pass --morphs NAMES or leave --model out")
        v, f = load_mesh(mesh)
        # A scanner's floor, turntable or pole is left out before anything sees it (its signed
        # volume, the embedding, bone heat). The glTF holds the body alone, renumbered: an artist
        # rigs a scan to animate the person; the floor is a capture artefact, and kept as an
        # unskinned node it would sit at the origin of every shot and come into Blender or Unity
        # as a second object to find and delete. The ids kept are in the asset's extras.
        found = scan_body(v, f, up=up, units=units, landmarks=weights if _has_landmarks(weights) else None)
        source = None
        if found is not None:
            source = (len(v), found.vertex_ids)
            for note in found.notes:
                console.print(f"[left out] {mesh}: {note}", markup=False, highlight=False)
            console.print(f"[left out] {mesh}: the glTF holds the body alone: {len(found.vertex_ids)} of {len(v)} "
                          "vertices, renumbered in their order (the mesh's ids in the asset's extras, "
                          "source_vertices)", markup=False, highlight=False)
            v, f = v[found.vertex_ids], found.faces
        if flip_winding:
            if not winding_inwards(v, f)[0]:
                raise ParameterError(f"--flip-winding: the faces of {mesh} are wound outwards already; leave "
                                     "--flip-winding out")
            f = np.ascontiguousarray(f[:, ::-1])
        body_model = BodyModel.load(model) if model is not None else None
        if body_model is not None and body_model.semantics is None:
            raise ParameterError(f"--model {model}: holds no semantic regressors; fit them once with bodyspace generate "
                                 f"{model} --database DB ... (they are saved into the model file)")
        said = write_rigged(out, v, f, rig_name, body_model=body_model, morphs=morphs, png=png, bones=bones,
                            where=str(mesh), up=up, units=units, weights_file=weights,
                            source_vertices=source)
    except BodyspaceError as exc:
        fail(exc)
    console.print(said, highlight=False)


def _has_landmarks(path: Optional[Path]) -> bool:
    """Whether a --weights file carries landmarks (``bodyspace landmarks`` writes them) that say
    which pieces of the mesh are the body; a file that cannot be read is refused later, naming it."""
    if path is None:
        return False
    try:
        return isinstance(d := json.loads(Path(path).read_text(encoding="utf-8")), dict) and "landmarks" in d
    except (OSError, ValueError):
        return False
