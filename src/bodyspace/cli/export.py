"""Rigged glTF from the command line: ``bodyspace rig MESH --out body.glb`` and the ``--rig``
branch of ``bodyspace generate`` (``write_rigged``), with ``--morphs`` and ``--png``.

A body of the template topology carries a CC0 rig: its skeleton is regressed from the body's
own vertices (``rig.skeleton.body_skeleton``) and MakeHuman's skin weights apply as they are.
The exporter (``export.gltf.write_gltf``) takes any mesh with any skeleton and weights, so
skeleton embedding and bone-heat weights for other topologies plug in at ``skeleton_and_weights``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np
import typer

from bodyspace.cli.common import ForceOption, check_file_output, console, fail
from bodyspace.data.template import RIG_NAMES, load_template
from bodyspace.errors import BodyspaceError, ParameterError
from bodyspace.export.gltf import write_gltf
from bodyspace.export.morphs import parse_morph_specs, semantic_morph_targets
from bodyspace.mesh.io import load_mesh
from bodyspace.model import BodyModel
from bodyspace.report.rig_figure import rig_figure
from bodyspace.rig.skeleton import body_skeleton

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


def skeleton_and_weights(vertices: np.ndarray, faces: np.ndarray, rig_name: str, where: str):
    """The skeleton and skin weights of a body for rig ``rig_name``: the template's rig when the
    body has the template topology (what ``where`` names otherwise says what was found)."""
    template = load_template()
    v, f = np.asarray(vertices), np.asarray(faces)
    if v.shape != template.vertices.shape or not np.array_equal(f, template.faces):
        raise ParameterError(f"{where}: {len(v)} vertices / {len(f)} faces; the CC0 rigs are defined on the template "
                             f"topology ({len(template.vertices)} vertices, {len(template.faces)} faces); a mesh of "
                             "another topology needs skeleton embedding and bone-heat weights (not part of this "
                             "command yet)")
    rig = template.rigs.get(rig_name)
    if rig is None:
        raise ParameterError(f"--rig {rig_name!r}: the asset folder has no such rig; it has "
                             f"{', '.join(template.rigs)}")
    return body_skeleton(rig, v, rest_vertices=template.vertices), rig.weights


def write_rigged(out: Path, vertices: np.ndarray, faces: np.ndarray, rig_name: str, *, body_model=None,
                 morphs: Optional[str] = None, png: Optional[Path] = None, bones: Optional[str] = None,
                 where: str = "the body") -> str:
    """Write the rigged ``.glb`` (and the ``--png``); returns a line saying what was written."""
    skeleton, weights = skeleton_and_weights(vertices, faces, rig_name, where)
    names = [b.strip() for b in bones.split(",")] if bones else None
    for b in names or []:
        if b not in skeleton.bone_names:
            raise ParameterError(f"--bones {b!r}: not a bone of rig {rig_name}; expected names such as "
                                 f"{', '.join(skeleton.bone_names[:8])}, ... ({skeleton.n_bones} bones)")
    targets = []
    if morphs is not None:
        if body_model is None:
            raise ParameterError("--morphs needs the model whose semantic variables they are; pass --model MODEL.npz")
        targets = semantic_morph_targets(body_model, vertices, parse_morph_specs(morphs))
    write_gltf(out, vertices, faces, skeleton, weights, targets,
               extras={"rig": rig_name, "template": load_template().template_id})
    said = f"wrote {out}: rig {rig_name} ({skeleton.n_bones} bones), {len(vertices)} vertices"
    if targets:
        said += ", morph targets " + ", ".join(t.name for t in targets)
    if png is not None:
        rig_figure(png, vertices, faces, skeleton, weights, bones=names,
                   title=f"{Path(out).name}: rig {rig_name}")
        said += f"; {png}"
    return said


def rig(mesh: Path = typer.Argument(..., help="A body mesh of the template topology (.obj, .ply or .glb; metres, "
                                              "+Y up), e.g. from bodyspace generate or sample."),
        out: Path = typer.Option(..., "--out", help="The rigged binary glTF to write (.glb)."),
        rig_name: str = typer.Option("default", "--rig", help="The CC0 rig: " + ", ".join(RIG_NAMES) + "."),
        model: Optional[Path] = typer.Option(None, "--model", help="With --morphs: the model file (with semantic "
                                                                   "regressors) whose variables they are."),
        morphs: Optional[str] = MorphsOption, png: Optional[Path] = PngOption, bones: Optional[str] = BonesOption,
        force: bool = ForceOption):
    """A rigged glTF 2.0 of a body: skeleton regressed from its vertices, MakeHuman's CC0 skin weights (4 per vertex),
    bind pose = the mesh as given; optionally morph targets of a model's semantic variables."""
    check_file_output(out, "--out", force, (".glb",), example="body.glb")
    try:
        check_rig_options(out, rig_name, morphs, png, bones, force)
        if model is not None and morphs is None:
            raise ParameterError("--model is read for --morphs only; pass --morphs NAMES or leave --model out")
        v, f = load_mesh(mesh)
        body_model = BodyModel.load(model) if model is not None else None
        if body_model is not None and body_model.semantics is None:
            raise ParameterError(f"--model {model}: holds no semantic regressors; fit them once with bodyspace generate "
                                 f"{model} --database DB ... (they are saved into the model file)")
        said = write_rigged(out, v, f, rig_name, body_model=body_model, morphs=morphs, png=png, bones=bones,
                            where=str(mesh))
    except BodyspaceError as exc:
        fail(exc)
    console.print(said, highlight=False)
