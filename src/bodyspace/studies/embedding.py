"""Embedding study: how close ``rig.embed.embed_skeleton`` puts the default rig's joints to the true
ones on bodies the model never saw (issue 13, "What it must show": an accuracy table per joint
group on at least 20 foreign-topology bodies).

Bodies: phenotypes at and beyond the edges of the population (``synth.foreign.foreign_phenotype``:
extreme muscle, proportions, weight, height, age 55-85 or 18-20, one-sided race mixes), each in
MakeHuman's A-pose ("rest") or the T-pose, alternately, posed on the ground by the rig, put on
one of several remeshed and reordered topologies (vertex counts ``vertex_counts``, one each) and
moved into another frame and unit, cycling through ``FRAMES`` (millimetres Z-up, centimetres
facing away, metres turned sideways, inches Z-up), which the embedding must find itself. The
truth is the rig's posed bone heads (``pose_bodies``), carried into the same frame.

Data only (``EmbeddingStudy``); ``markdown`` formats the table.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from bodyspace.data.template import Template
from bodyspace.errors import ParameterError
from bodyspace.rig.embed import JOINT_GROUPS, embed_skeleton, joint_group
from bodyspace.synth.foreign import foreign_body, foreign_topology
from bodyspace.synth.phenotype import PhenotypeModel
from bodyspace.validation import as_generator

__all__ = ["EmbeddingStudy", "FRAMES", "embedding_study", "markdown"]

# Frames the bodies are written in (``to_frame`` arguments), cycled through.
FRAMES = (
    dict(up="z", scale=1000.0, yaw_degrees=25.0, translation=(0.42, -0.17, 0.93)),     # Blender-like, mm
    dict(up="y", scale=100.0, yaw_degrees=-140.0, translation=(-1.2, 0.4, 2.5)),        # cm, facing away
    dict(up="y", scale=1.0, yaw_degrees=70.0, translation=(0.0, -0.05, 0.0)),           # m, turned sideways
    dict(up="z", scale=1 / 0.0254, yaw_degrees=180.0, translation=(3.0, 1.0, 0.0)),     # inches, Z up
)
POSES = ("rest", "t_pose")


@dataclass
class EmbeddingStudy:
    """Joint errors of N embedded bodies.

    bone_names: (B,) the default rig's; errors_m: (N, B) distance of each embedded joint from the
    true one (metres); seconds: (N,) wall time of each ``embed_skeleton`` call; residual_m: (N,)
    the fit's RMS surface distance; poses, units, ups: (N,) what each body was;
    vertex_counts: (N,); found_frame: (N,) bool, up axis and unit found as they were written.
    """

    bone_names: tuple[str, ...]
    errors_m: np.ndarray
    seconds: np.ndarray
    residual_m: np.ndarray
    poses: list[str]
    units: list[str]
    ups: list[str]
    vertex_counts: np.ndarray
    found_frame: np.ndarray

    def group_table(self) -> list[tuple[str, int, float, float, str]]:
        """(group, joints, mean error m, worst error m, worst bone) for every joint group and all."""
        groups = np.array([joint_group(b) for b in self.bone_names])
        rows = []
        for name in [g for g, _ in JOINT_GROUPS] + ["all joints"]:
            cols = np.ones(len(groups), bool) if name == "all joints" else groups == name
            e = self.errors_m[:, cols]
            worst = np.unravel_index(np.argmax(e), e.shape)
            rows.append((name, int(cols.sum()), float(e.mean()), float(e.max()),
                         np.asarray(self.bone_names)[cols][worst[1]]))
        return rows


_UNIT_NAMES = {1000.0: "mm", 100.0: "cm", 1.0: "m", 1 / 0.0254: "in"}


def embedding_study(template: Template, phenotype_model: PhenotypeModel, n_bodies: int = 24,
                    vertex_counts=(3000, 6000, 12000), rng=None) -> EmbeddingStudy:
    """Embed the default rig into ``n_bodies`` foreign bodies and compare with their true joints."""
    if n_bodies < 1:
        raise ParameterError(f"n_bodies={n_bodies}; expected at least 1")
    rng = as_generator(rng)
    topologies = [foreign_topology(template, int(n), rng) for n in vertex_counts]
    names = template.rigs["default"].bone_names
    errors, seconds, residual, poses, units, ups, counts, found = [], [], [], [], [], [], [], []
    for i in range(n_bodies):
        frame = FRAMES[i % len(FRAMES)]
        pose = POSES[i % len(POSES)]
        topo = topologies[(i // 2) % len(topologies)]
        fb = foreign_body(template, phenotype_model, topo, rng, pose=pose, frame=frame)
        t0 = time.perf_counter()
        emb = embed_skeleton(fb.vertices, fb.faces, mesh_name=f"body {i}")
        seconds.append(time.perf_counter() - t0)
        errors.append(np.linalg.norm(emb.joints - fb.true_joints, axis=1) / frame["scale"])
        residual.append(emb.residual_m)
        unit = _UNIT_NAMES[frame["scale"]]
        poses.append(pose), units.append(unit), ups.append(frame["up"]), counts.append(topo.n_vertices)
        found.append(emb.frame.up == frame["up"] and emb.frame.units == unit)
    return EmbeddingStudy(tuple(names), np.array(errors), np.array(seconds), np.array(residual), poses, units, ups,
                          np.array(counts), np.array(found))


def markdown(study: EmbeddingStudy) -> str:
    """The accuracy table (cm) and a line on time and frames."""
    lines = ["| joint group | joints | mean error (cm) | worst error (cm) | worst bone |",
             "|---|---:|---:|---:|---|"]
    for name, n, mean, worst, bone in study.group_table():
        bold = "**" if name == "all joints" else ""
        lines.append(f"| {bold}{name}{bold} | {n} | {bold}{100 * mean:.2f}{bold} | {bold}{100 * worst:.2f}{bold} | "
                     f"{bone} |")
    per_body_mean = study.errors_m.mean(axis=1)
    per_body_worst = study.errors_m.max(axis=1)
    n = len(study.seconds)
    lines.append("")
    lines.append(f"{n} bodies ({study.poses.count('rest')} A-pose, {study.poses.count('t_pose')} T-pose; "
                 f"{', '.join(str(c) for c in sorted(set(study.vertex_counts.tolist())))} vertices; units "
                 f"{', '.join(sorted(set(study.units)))}; up {', '.join(sorted(set(study.ups)))}). Per body: mean joint "
                 f"error {100 * per_body_mean.min():.2f}-{100 * per_body_mean.max():.2f} cm, worst joint "
                 f"{100 * per_body_worst.min():.2f}-{100 * per_body_worst.max():.2f} cm; up axis and unit found "
                 f"from the mesh on {int(study.found_frame.sum())}/{n}; fit residual "
                 f"{1000 * study.residual_m.min():.1f}-{1000 * study.residual_m.max():.1f} mm RMS; time per mesh "
                 f"median {np.median(study.seconds):.2f} s, max {study.seconds.max():.2f} s.")
    return "\n".join(lines)
