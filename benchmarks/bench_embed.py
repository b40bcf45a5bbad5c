"""Skeleton embedding (rig/embed.py): time per mesh against a baseline in the same run, and the
whole ``bodyspace rig`` pipeline on foreign meshes of several vertex counts.

Speed: ``embed_skeleton`` (the fit's Jacobian exact and analytic: rotations as subtree turns
about the posed joints, shape through vertices and joints) against the same fit whose Jacobian
is taken by central finite differences of the posed vertices (what ``scipy.optimize.least_squares``
would do by default: two evaluations per parameter, 232 a round), in the same run; both must
place the joints alike. Then per vertex count: embedding, every bone of the default rig
(``embedded_skeleton``), bone-heat weights on the mesh, and the glTF bytes. Target: under 10 s a
mesh (issue 13).

Run: python benchmarks/bench_embed.py
"""

from __future__ import annotations

import time

import numpy as np

import bodyspace.rig.embed as embed
from bodyspace.data.template import load_template
from bodyspace.export.gltf import gltf_bytes
from bodyspace.rig.weights import bone_heat_weights
from bodyspace.synth.foreign import foreign_body, foreign_topology
from bodyspace.synth.phenotype import PhenotypeModel

_analytic = embed._jacobian


def finite_difference_jacobian(model, st, ids, heads, G, eps: float = 1e-6):
    """The baseline: d(posed vertices)/d(parameters) by central differences, (n, 3, 3P + K + 4)."""
    _, G0 = embed._pose(model, st)
    n_par = 3 * len(model.fitted) + len(st.c) + 4
    J = np.empty((len(ids), 3, n_par))
    for k in range(n_par):
        step = np.zeros(n_par)
        step[k] = eps
        plus = embed._apply_step(model, st, step, G0)
        minus = embed._apply_step(model, st, -step, G0)
        J[:, :, k] = (embed._posed(model, plus, ids, embed._pose(model, plus)[1])
                      - embed._posed(model, minus, ids, embed._pose(model, minus)[1])) / (2 * eps)
    return embed._posed(model, st, ids, G0), J


def main() -> None:
    template = load_template()
    pm = PhenotypeModel(template)
    rng = np.random.default_rng(13)
    t0 = time.perf_counter()
    embed._model()
    print(f"template model for the fit (shape directions, regressed heads; once per process): "
          f"{time.perf_counter() - t0:.2f} s")
    topo = foreign_topology(template, 6000, rng)
    bodies = [foreign_body(template, pm, topo, rng, pose=p) for p in ("rest", "t_pose")]
    embed.embed_skeleton(bodies[0].vertices, bodies[0].faces, iterations=2)       # compile, warm caches
    fast, slow, diff = [], [], []
    for fb in bodies:
        t = time.perf_counter()
        a = embed.embed_skeleton(fb.vertices, fb.faces)
        fast.append(time.perf_counter() - t)
        embed._jacobian = finite_difference_jacobian
        try:
            t = time.perf_counter()
            b = embed.embed_skeleton(fb.vertices, fb.faces)
            slow.append(time.perf_counter() - t)
        finally:
            embed._jacobian = _analytic
        diff.append(float(np.abs(a.joints - b.joints).max() / fb.frame["scale"]))
        err = np.linalg.norm(a.joints - fb.true_joints, axis=1) / fb.frame["scale"]
        print(f"  {fb.pose}: analytic {fast[-1]:.2f} s ({a.rounds} rounds), finite differences {slow[-1]:.2f} s "
              f"({b.rounds} rounds); joints differ by at most {1000 * diff[-1]:.2f} mm; mean joint error "
              f"{100 * err.mean():.2f} cm")
    print(f"embed_skeleton, 6,000-vertex foreign bodies: {sum(fast) / len(fast):.2f} s a mesh (baseline "
          f"{sum(slow) / len(slow):.2f} s a mesh), speed-up x{sum(slow) / sum(fast):.1f}")

    print("bodyspace rig pipeline per mesh (A-pose, mm, Z up), default rig (163 bones):")
    rig = template.rigs["default"]
    deform = np.asarray(abs(rig.weights).sum(axis=0)).ravel() > 0
    for n in (3000, 6000, 12000, 24000):
        topo = foreign_topology(template, n, rng)
        fb = foreign_body(template, pm, topo, rng, pose="rest")
        t = time.perf_counter()
        emb = embed.embed_skeleton(fb.vertices, fb.faces)
        t_embed = time.perf_counter() - t
        t = time.perf_counter()
        skeleton = embed.embedded_skeleton(emb, rig)
        t_skel = time.perf_counter() - t
        body = emb.frame.to_internal(fb.vertices)
        t = time.perf_counter()
        weights = bone_heat_weights(body, fb.faces, skeleton.heads, skeleton.tails, deform=deform)
        t_heat = time.perf_counter() - t
        t = time.perf_counter()
        gltf_bytes(body, fb.faces, skeleton, weights)
        t_gltf = time.perf_counter() - t
        err = np.linalg.norm(emb.joints - fb.true_joints, axis=1) / fb.frame["scale"]
        print(f"  {topo.n_vertices:6d} vertices: embedding {t_embed:.2f} s ({emb.rounds} rounds), skeleton "
              f"{t_skel:.3f} s, bone heat {t_heat:.2f} s, glTF {t_gltf:.2f} s, total "
              f"{t_embed + t_skel + t_heat + t_gltf:.2f} s; mean joint error {100 * err.mean():.2f} cm, worst "
              f"{100 * err.max():.2f} cm")


if __name__ == "__main__":
    main()
