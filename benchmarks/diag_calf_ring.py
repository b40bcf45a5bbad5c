"""Why remeshed bodies' calf girths are short (issue 15, docs/registration.md "Landmarks for any
topology"): the calf plane of the true body (the `calf` landmark, normal knee -> ankle joint) cut
through the template's mesh and through the remeshed one (``synth.foreign.foreign_body``, the
landmark study's bodies, seeds 200 + i), each ring's convex hull perimeter; and the same with every
crossing moved onto its edge's curved PN-triangle curve (cubic Bezier from the two vertex normals),
a prototype of a girth that follows the surface's curvature between crossings. Prints the gap
remeshed - template, both ways, and how far the curve moves the template's own value.

    python benchmarks/diag_calf_ring.py [--bodies 12] [--vertices 15000]
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.spatial import ConvexHull

from bodyspace.data.template import load_template
from bodyspace.errors import MeshError
from bodyspace.measure import load_measurement_set
from bodyspace.mesh.geometry import vertex_normals
from bodyspace.synth.foreign import foreign_body
from bodyspace.synth.phenotype import PhenotypeModel

POSES = ("rest", "t_pose", "step_forward_left", "arms_forward")
REACH = 0.09       # crossings farther than this (m) from the limb axis are another limb's


def ring_perimeter(V, F, origin, normal, centre, curved: bool) -> float:
    """Convex hull perimeter (m) of the plane's crossings of the mesh's edges near ``centre``
    (V (n, 3), F (m, 3)); ``curved``: each crossing on its edge's PN-triangle curve."""
    N = vertex_normals(V, F)
    E = np.unique(np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1), axis=0)
    h = (V - origin) @ normal
    cut = h[E[:, 0]] * h[E[:, 1]] < 0
    a, b = E[cut, 0], E[cut, 1]
    s = (h[a] / (h[a] - h[b]))[:, None]
    A, B = V[a], V[b]
    if curved:
        b1 = A + (B - A) / 3 - ((B - A) * N[a]).sum(1, keepdims=True) * N[a] / 3
        b2 = B + (A - B) / 3 - ((A - B) * N[b]).sum(1, keepdims=True) * N[b] / 3
        P = (1 - s) ** 3 * A + 3 * (1 - s) ** 2 * s * b1 + 3 * (1 - s) * s ** 2 * b2 + s ** 3 * B
    else:
        P = A + s * (B - A)
    d = P - centre
    P = P[np.linalg.norm(d - (d @ normal)[:, None] * normal, axis=1) < REACH]
    u = np.cross(normal, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(normal, u)
    xy = np.c_[(P - centre) @ u, (P - centre) @ w]
    hull = xy[ConvexHull(xy).vertices]
    return float(np.linalg.norm(hull - np.roll(hull, 1, axis=0), axis=1).sum())


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--bodies", type=int, default=12)
    ap.add_argument("--vertices", type=int, default=15000)
    args = ap.parse_args()
    template = load_template()
    pm = PhenotypeModel(template)
    mset = load_measurement_set()
    L = mset.landmark_matrix(template.n_vertices)
    ix = {n: i for i, n in enumerate(mset.landmark_names)}
    gaps = []
    for i in range(args.bodies):
        try:
            body = foreign_body(template, pm, rng=200 + i, pose=POSES[i % 4], target_vertices=args.vertices)
        except MeshError:
            body = foreign_body(template, pm, rng=300 + i, pose=POSES[i % 4], target_vertices=args.vertices)
        T, X = body.template_vertices, body.internal_vertices()
        X = X - [0.0, X[:, 1].min() - T[:, 1].min(), 0.0]      # both on the same floor
        P = L @ T
        for side in "lr":
            o = P[ix[f"calf_{side}"]]
            knee, ankle = P[ix[f"knee_joint_{side}"]], P[ix[f"ankle_joint_{side}"]]
            n = (ankle - knee) / np.linalg.norm(ankle - knee)
            c = knee + ((o - knee) @ n) * n
            r = [1000 * ring_perimeter(M, F, o, n, c, curved) for curved in (False, True)
                 for M, F in ((T, template.faces), (X, body.faces))]
            gaps.append((r[1] - r[0], r[3] - r[2], r[2] - r[0]))
            print(f"body {i} ({body.pose}) {side}: template {r[0]:.1f} mm, remeshed {r[1] - r[0]:+.1f}; "
                  f"curved: template {r[2]:.1f}, remeshed {r[3] - r[2]:+.1f}", flush=True)
    g = np.array(gaps)
    print(f"remeshed - template over {len(g)} calves: straight edges {g[:, 0].mean():+.2f} mm (median "
          f"{np.median(g[:, 0]):+.2f}), curved {g[:, 1].mean():+.2f} (median {np.median(g[:, 1]):+.2f}); "
          f"the curve moves the template's own value by {g[:, 2].mean():+.2f} mm (median {np.median(g[:, 2]):+.2f})")


if __name__ == "__main__":
    main()
