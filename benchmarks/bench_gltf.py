"""Rigged glTF export: speed against trimesh's plain exporter, and what 4 influences cost.

1. Export of one rigged body (default rig, 163 bones) with 8 morph targets (skeleton for the
   body, 4 influences, normals of the body and of every target, GLB bytes) against trimesh's
   GLB export of the same mesh without rig or morphs, in the same run. Target: under 1 s.
2. Dropping influences beyond 4 (glTF's JOINTS_0/WEIGHTS_0): per rig, how many vertices have
   more, and how far linear blend skinning with the 4 largest (renormalized) lands from
   skinning with all of them, over every pose of the library on a few bodies (mm).

Run: python benchmarks/bench_gltf.py
"""

from __future__ import annotations

import io
import sys
import time
from pathlib import Path

import numpy as np
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import best_time  # noqa: E402

from bodyspace.data.template import RIG_NAMES, load_template  # noqa: E402
from bodyspace.export.gltf import MorphTarget, gltf_bytes, influences_matrix, top_influences  # noqa: E402
from bodyspace.errors import ParameterError  # noqa: E402
from bodyspace.rig.kinematics import forward_kinematics, linear_blend_skinning, rotvec_to_matrix  # noqa: E402
from bodyspace.rig.skeleton import body_skeleton  # noqa: E402
from bodyspace.synth.phenotype import PARAMETERS, PhenotypeModel  # noqa: E402
from bodyspace.synth.poses import load_pose_library  # noqa: E402


def export_speed(template, phenotype) -> None:
    rng = np.random.default_rng(0)
    bodies = phenotype.vertices(rng.random((9, len(PARAMETERS))))
    body, others = bodies[0], bodies[1:]
    morphs = [MorphTarget(f"morph {i}", o - body) for i, o in enumerate(others)]   # 8 shape keys
    rig = template.rigs["default"]

    def rigged():
        return gltf_bytes(body, template.faces, body_skeleton(rig, body, rest_vertices=template.vertices),
                          rig.weights, morphs)

    def plain():
        buf = io.BytesIO()
        trimesh.Trimesh(body, template.faces, process=False).export(buf, file_type="glb")
        return buf.getvalue()

    rigged(), plain()
    t_skel = best_time(lambda: body_skeleton(rig, body, rest_vertices=template.vertices), repeat=5)
    t_rig = best_time(rigged, repeat=5)
    t_plain = best_time(plain, repeat=5)
    t0 = time.perf_counter()
    gltf_bytes(body, template.faces)
    t_ours_plain = time.perf_counter() - t0
    print(f"export, one body of {len(body):,} vertices: rigged ({rig.n_bones} bones, skeleton {1000 * t_skel:.0f} ms "
          f"included) + 8 morph targets {1000 * t_rig:.0f} ms ({len(rigged()) / 1e6:.1f} MB); trimesh's plain GLB "
          f"{1000 * t_plain:.0f} ms ({len(plain()) / 1e6:.1f} MB); ours plain {1000 * t_ours_plain:.0f} ms; "
          f"ratio rigged+morphs / trimesh plain x{t_rig / t_plain:.2f}; target < 1 s: "
          f"{'met' if t_rig < 1.0 else 'NOT met'}")


def influence_cost(template, phenotype, n_bodies: int = 4) -> None:
    library = load_pose_library()
    bodies = phenotype.vertices({"gender": np.array([1.0, 0.0, 1.0, 0.0])[:n_bodies],
                                 "weight": np.array([0.5, 0.5, 1.0, 0.9])[:n_bodies],
                                 "muscle": np.array([0.5, 0.5, 0.0, 1.0])[:n_bodies]})
    print(f"\ndropping influences beyond 4: {n_bodies} bodies x the {len(library.names)} poses of the library "
          "(default rigs; the library names their bones) or 40 random poses (other rigs: every bone turned by "
          "N(0, 15 deg) about each axis)")
    print("| rig | vertices with > 4 influences | dropped weight to | max error (mm) | 99th percentile (mm) | mean (mm) "
          "| worst pose |")
    print("|---|---|---|---|---|---|---|")
    for name in RIG_NAMES:
        rig = template.rigs[name]
        more = int((np.diff(rig.weights.tocsr().indptr) > 4).sum())
        try:
            R, names = library.stack(library.names, rig), library.names        # (P, B, 3, 3)
        except ParameterError:   # the library names bones of the default rig only: random poses instead
            R = rotvec_to_matrix(np.random.default_rng(1).normal(0.0, np.radians(15), (40, rig.n_bones, 3)))
            names = [f"random pose {i}" for i in range(40)]
        for how, parents in (("kept kin", rig.parents), ("renormalized", None)):
            j, w = top_influences(rig.weights, parents=parents)
            W4 = influences_matrix(j, w, rig.n_bones)
            errs, worst = [], (0.0, "")
            for v in bodies:
                G = forward_kinematics(R, rig.heads(v), rig.parents)
                d = np.linalg.norm(linear_blend_skinning(v, rig.weights, G) - linear_blend_skinning(v, W4, G), axis=2)
                errs.append(d.ravel())
                p = int(np.argmax(d.max(axis=1)))
                if d[p].max() > worst[0]:
                    worst = (float(d[p].max()), names[p])
            e = 1000 * np.concatenate(errs)
            print(f"| {name} | {more:,} of {template.n_vertices:,} | {how} | {e.max():.1f} | {np.percentile(e, 99):.2f} | "
                  f"{e.mean():.3f} | {worst[1]} |")


def main() -> None:
    template = load_template()
    phenotype = PhenotypeModel(template)
    export_speed(template, phenotype)
    influence_cost(template, phenotype)


if __name__ == "__main__":
    main()
