"""Relative rotation encoding and vertex encoding: round trips, invariance, interpolation,
constraints, bad input."""

import numpy as np
import pytest
import trimesh
from _meshes import open_tube
from scipy.spatial.transform import Rotation

from bodyspace.encoding import (
    PositionConstraints,
    RelativeRotationEncoder,
    VertexEncoder,
)
from bodyspace.encoding.rotations import (
    polar_decomposition,
    project_to_rotations,
    quaternion_from_matrix,
    quaternion_log,
    rotation_exp,
    rotation_log,
)
from bodyspace.errors import MeshError, ParameterError
from bodyspace.mesh.alignment import rigid_procrustes
from bodyspace.shape.compare import interpolation_distortion

RNG = np.random.default_rng(7)


def tube(rings=24, around=12, length=0.8, radius=0.06):
    """Open cylinder along +y (two boundary loops), rings of ``around`` vertices."""
    return open_tube(rings, around, length, radius)


def bend(v, angle, joint=0.4, band=0.15):
    """Bend a +y limb at ``joint``: rings above it turn about the x axis through the joint by up
    to ``angle``, ramping smoothly across the band (an elbow)."""
    w = np.clip((v[:, 1] - (joint - band)) / (2 * band), 0, 1)
    w = w * w * (3 - 2 * w)
    out = v.copy()
    for i, (p, wi) in enumerate(zip(v, w)):
        r = Rotation.from_rotvec([angle * wi, 0, 0]).as_matrix()
        out[i] = r @ (p - [0, joint, 0]) + [0, joint, 0]
    return out


def smooth_deform(v, amplitude=0.05, seed=0):
    """A smooth random displacement plus a random rigid motion."""
    rng = np.random.default_rng(seed)
    k = rng.normal(size=(3, 3)) * 2
    phase = rng.uniform(0, 2 * np.pi, 3)
    x = v + amplitude * np.sin(v @ k.T + phase)
    return x @ Rotation.random(random_state=seed).as_matrix().T + rng.normal(size=3)


def height(v):
    return np.ptp(v[..., 1], axis=-1).max()


def aligned(x, ref, parts=None):
    """x rigidly aligned to ref, part by part (vertex index arrays), as decode places bodies."""
    parts = parts or [np.arange(x.shape[-2])]
    out = np.empty_like(x)
    for p in parts:
        out[..., p, :] = rigid_procrustes(x[..., p, :], ref[p])[0]
    return out


@pytest.fixture(scope="module")
def sphere():
    m = trimesh.creation.icosphere(subdivisions=3)
    return np.asarray(m.vertices) * 0.85, np.asarray(m.faces)


# ---------------------------------------------------------------------------- rotations

def test_rotation_helpers():
    r = Rotation.random(200, random_state=1)
    m = r.as_matrix()
    np.testing.assert_allclose(rotation_exp(rotation_log(m)), m, atol=1e-12)
    np.testing.assert_allclose(np.abs(quaternion_from_matrix(m)), np.abs(r.as_quat()[:, [3, 0, 1, 2]]), atol=1e-12)
    small = np.array([[1e-12, -3e-13, 2e-12], [0, 0, 0]])
    np.testing.assert_allclose(rotation_log(rotation_exp(small)), small, atol=1e-20)
    near_pi = np.array([[np.pi - 1e-9, 0, 0]])
    np.testing.assert_allclose(np.abs(rotation_log(rotation_exp(near_pi))), np.abs(near_pi), atol=1e-7)
    assert np.all(np.linalg.norm(quaternion_log(quaternion_from_matrix(m)), axis=-1) <= np.pi + 1e-12)
    u = m @ (np.eye(3) + 0.3 * np.random.default_rng(0).normal(size=(200, 3, 3)) * [[1, 0.5, 0.2]])
    u = u[np.linalg.det(u) > 0.05]
    rot, s = polar_decomposition(u)
    np.testing.assert_allclose(rot @ s, u, atol=1e-10)
    np.testing.assert_allclose(s, np.swapaxes(s, -1, -2), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rot), 1, atol=1e-12)
    # Projection handles det <= 0 by the SVD with a flipped axis: still a rotation.
    bad = -np.eye(3)[None] * [1, 1, 1]
    np.testing.assert_allclose(np.linalg.det(project_to_rotations(bad)), 1, atol=1e-12)


# ---------------------------------------------------------------------------- round trips

def test_round_trip_closed_mesh_and_rotation_invariance(sphere):
    v, f = sphere
    scans = np.stack([smooth_deform(v, 0.06, s) for s in range(4)])
    enc = RelativeRotationEncoder(v, f).fit(scans)
    codes = enc.encode(scans)
    assert codes.shape == (4, 15 * len(f))
    out = enc.decode(codes)
    tol = 1e-6 * height(scans)
    assert np.abs(out - aligned(scans, enc.mean_vertices_)).max() < tol
    assert enc.last_factorized_ == 0  # consistent codes: the tree rotations are exact
    # Locally rotation invariant encoding: a rigid motion does not change the code.
    moved = scans[1] @ Rotation.random(random_state=3).as_matrix().T + [1.0, -2.0, 0.5]
    np.testing.assert_allclose(enc.encode(moved)[0], codes[1], atol=1e-9)
    # (D,) in, (1, V, 3) out; batch equals one at a time.
    np.testing.assert_allclose(enc.decode(codes[2])[0], out[2], atol=1e-9)


def test_round_trip_boundary_and_two_parts(sphere):
    v, f = tube()
    nb = RelativeRotationEncoder(v, f)
    assert (~nb.slot_mask_).sum() == 2 * 12
    v2, f2 = sphere
    # A tube and a sphere in one mesh: two parts, each anchored and placed on its own.
    verts = np.concatenate([v, v2 + [1.0, 0, 0]])
    faces = np.concatenate([f, f2 + len(v)])
    scans = np.stack([np.concatenate([bend(v, a), smooth_deform(v2, 0.05, s)]) for s, a in [(0, 0.3), (1, -0.8)]])
    enc = RelativeRotationEncoder(verts, faces).fit(scans)
    assert len(enc.anchor_faces) == 2
    codes = enc.encode(scans)
    assert np.all(codes.reshape(2, -1, 15)[:, :len(f), :9].reshape(2, len(f), 3, 3)[:, ~nb.slot_mask_] == 0)
    parts = [np.arange(len(v)), np.arange(len(v), len(verts))]
    out = enc.decode(codes)
    assert np.abs(out - aligned(scans, enc.mean_vertices_, parts)).max() < 1e-6 * height(scans)


def test_decode_of_modified_codes_matches_direct_solve(sphere):
    v, f = sphere
    scans = np.stack([smooth_deform(v, 0.12, s) for s in range(3)])
    enc = RelativeRotationEncoder(v, f).fit(scans)
    codes = enc.encode(scans)
    mixed = np.stack([0.5 * (codes[0] + codes[1]), 0.3 * codes[2] - 0.4 * codes[0],
                      codes[1] + 1e-3 * RNG.normal(size=codes.shape[1])])
    batch = enc.decode(mixed)
    assert enc.last_factorized_ == 3  # inconsistent codes: each needs its factorization
    one = np.concatenate([enc.decode(c) for c in mixed])  # one body: on two lanes
    enc.rotation_solver = "direct"
    ref = enc.decode(mixed)
    assert np.abs(batch - ref).max() < 1e-9 * height(scans)
    assert np.abs(one - ref).max() < 1e-9 * height(scans)


def test_rotation_solver_names():
    v, f = tube()
    assert RelativeRotationEncoder(v, f, rotation_solver="pcg").rotation_solver == "exact"  # older files
    with pytest.raises(ParameterError, match="rotation_solver"):
        RelativeRotationEncoder(v, f, rotation_solver="cg")
    with pytest.raises(ParameterError, match="on_flipped='banana', expected one of accept, warn, raise, ignore"):
        RelativeRotationEncoder(v, f, on_flipped="banana")


def test_vertex_encoder_round_trip(sphere):
    v, f = sphere
    scans = np.stack([smooth_deform(v, 0.06, s) for s in range(3)])
    enc = VertexEncoder(v, f).fit(scans)
    codes = enc.encode(scans)
    assert codes.shape == (3, 3 * len(v))
    np.testing.assert_allclose(codes.reshape(3, -1, 3).mean(0), 0, atol=1e-9)  # GPA mean
    out = enc.decode(codes)
    assert np.abs(out - aligned(scans, enc.mean_vertices_)).max() < 1e-9


# ---------------------------------------------------------------------------- interpolation

def test_halfway_pose_intact_with_rre_collapsed_with_vertices():
    v, f = tube()
    a, b = bend(v, 0.0), bend(v, 2.4)  # straight and bent by 137 degrees: one subject, two poses
    results = {}
    for name, cls in [("rre", RelativeRotationEncoder), ("vertex", VertexEncoder)]:
        enc = cls(v, f).fit(np.stack([a, b]))
        results[name] = interpolation_distortion(enc, a, b)
    rre, vtx = results["rre"], results["vertex"]
    assert rre["edge_change"] < 0.02 and abs(rre["volume_change"]) < 0.03
    assert vtx["edge_change"] > 5 * rre["edge_change"]
    assert vtx["volume_change"] < -0.1  # the forearm shortens towards the chord: volume is lost
    # The RRE halfway limb bends about halfway (68 degrees) and keeps its length.
    mid = rre["mesh"]
    top = mid[-12:].mean(0) - mid[:12].mean(0)
    assert abs(np.linalg.norm(top) - np.linalg.norm(bend(v, 1.2)[-12:].mean(0) - v[:12].mean(0))) < 0.01


# ---------------------------------------------------------------------------- constraints

def test_decode_with_positional_constraints():
    v, f = tube()
    scans = np.stack([bend(v, 0.0), bend(v, 1.0)])
    enc = RelativeRotationEncoder(v, f).fit(scans)
    code = enc.encode(scans[1])
    free = enc.decode(code)[0]
    tip = np.arange(len(v) - 12, len(v))
    target = free[tip] + [0.0, 0.05, 0.0]
    held = enc.decode(code, PositionConstraints(tip, target, weight=1e4))[0]
    assert np.abs(held[tip] - target).max() < 2e-3
    base = np.arange(12)
    assert np.abs(held[base] - free[base]).max() < 0.05  # the far end barely moves
    # Batch of constraint positions, one per body.
    many = enc.decode(np.repeat(code, 2, axis=0), PositionConstraints(tip, np.stack([target, free[tip]]), 1e4))
    np.testing.assert_allclose(many[0], held, atol=1e-9)
    assert np.abs(many[1] - free).max() < 1e-3
    # Same interface on the vertex encoding.
    venc = VertexEncoder(v, f).fit(scans)
    vheld = venc.decode(venc.encode(scans[1]), PositionConstraints(tip, target, 1e4))[0]
    assert np.abs(vheld[tip] - target).max() < 2e-3


# ---------------------------------------------------------------------------- bad input

@pytest.fixture(scope="module")
def fitted(sphere):
    v, f = sphere
    return RelativeRotationEncoder(v, f, on_flipped="raise").fit(v[None]), v, f


def test_not_fitted(sphere):
    v, f = sphere
    with pytest.raises(MeshError, match="not fitted"):
        RelativeRotationEncoder(v, f).encode(v)


@pytest.mark.parametrize("case, message", [
    ("vertex_count", "vertices per mesh, the template has"),
    ("nan", "NaN"),
    ("wrong_faces", "face 0 is"),
    ("degenerate", "degenerate triangle"),
    ("mirrored", "inside out"),
    ("fold", "flipped triangle"),
])
def test_encode_rejects_bad_meshes(fitted, case, message):
    enc, v, f = fitted
    x, faces = v.copy(), None
    if case == "vertex_count":
        x = x[:-1]
    elif case == "nan":
        x[10, 1] = np.nan
    elif case == "wrong_faces":
        faces = f.copy()
        faces[0] = faces[0, ::-1]
    elif case == "degenerate":
        a, b, c = f[5]
        x[a] = x[b]  # triangle 5 collapses onto an edge
    elif case == "mirrored":
        x[:, 0] *= -1
    elif case == "fold":
        # Swap the two ends of an edge: the two triangles on that edge turn over in place.
        i, j = f[0, 0], f[0, 1]
        x[[i, j]] = x[[j, i]]
    with pytest.raises(MeshError, match=message):
        enc.encode(x, faces)


def test_fold_policy_warn(sphere):
    v, f = sphere
    enc = RelativeRotationEncoder(v, f, on_flipped="warn").fit(v[None])
    x = v.copy()
    x[[f[0, 0], f[0, 1]]] = x[[f[0, 1], f[0, 0]]]
    with pytest.warns(RuntimeWarning, match="flipped"):
        code = enc.encode(x)
    assert np.abs(enc.decode(code)[0] - aligned(x[None], enc.mean_vertices_)[0]).max() < 1e-6
    assert enc.last_flipped_.tolist() == [2]  # the two triangles on the swapped edge


def test_fold_policy_accept_is_the_default_and_counts_per_mesh(sphere, recwarn):
    v, f = sphere
    enc = RelativeRotationEncoder(v, f).fit(v[None])
    assert enc.on_flipped == "accept"
    x = v.copy()
    x[[f[0, 0], f[0, 1]]] = x[[f[0, 1], f[0, 0]]]
    codes = enc.encode(np.stack([v, x, x]))
    assert enc.last_flipped_.tolist() == [0, 2, 2] and not recwarn.list
    assert np.abs(enc.decode(codes[1])[0] - aligned(x[None], enc.mean_vertices_)[0]).max() < 1e-6
    enc.on_flipped = "ignore"
    enc.encode(x)
    assert enc.last_flipped_.tolist() == [0]  # not looked for


@pytest.mark.parametrize("codes, message", [
    (np.zeros(7), "expected"),
    (np.zeros((2, 3, 4)), "expected"),
    ("nan", "NaN"),
])
def test_decode_rejects_bad_codes(fitted, codes, message):
    enc, v, f = fitted
    if isinstance(codes, str):
        codes = np.zeros(enc.n_features_)
        codes[17] = np.nan
    with pytest.raises(MeshError, match=message):
        enc.decode(codes)
    with pytest.raises(MeshError, match=str(enc.n_features_)):
        enc.decode(np.zeros(enc.n_features_ + 15))


def test_template_rejects_degenerate_faces(sphere):
    v, f = sphere
    v = v.copy()
    a, b = sorted((int(f[3, 0]), int(f[3, 1])))
    v[a] = v[b]                                  # two vertices at one point, as a remesher leaves them
    with pytest.raises(MeshError) as info:
        RelativeRotationEncoder(v, f)
    message = str(info.value)
    assert "zero-area face(s)" in message and "3" in message
    assert f"vertices {a} and {b}" in message, message
    assert "weld coincident vertices" in message and "--encoding vertex" in message


# ---------------------------------------------------------------------------- real template
def test_fixed_pattern_factorization_matches_direct_solve(sphere):
    """The exact path (anchor columns eliminated, one symbolic analysis reused by every body)
    equals the per-body SuperLU baseline, with boundaries and two parts, for codes far from
    consistent, one at a time, in a batch and on two threads."""
    v, f = tube()
    v2, f2 = sphere
    verts = np.concatenate([v, v2 + [1.0, 0, 0]])
    faces = np.concatenate([f, f2 + len(v)])
    scans = np.stack([np.concatenate([bend(v, a), smooth_deform(v2, 0.1, s)])
                      for s, a in [(0, 0.4), (1, -0.9), (2, 1.3)]])
    enc = RelativeRotationEncoder(verts, faces).fit(scans)
    codes = enc.encode(scans)
    wild = np.stack([2.0 * codes[0] - 1.5 * codes[1] + codes[2], 0.5 * (codes[1] + codes[2]),
                     codes[0] + 0.2 * RNG.normal(size=codes.shape[1])])
    rel = enc.relative_rotations(wild)
    direct = enc.solve_rotations(rel, "direct")
    for _ in range(2):  # the second call reuses the analysed pattern (numeric update only)
        exact = enc.solve_rotations(rel, "exact")
        assert enc.last_factorized_ == len(wild)
        np.testing.assert_allclose(exact, direct, atol=1e-9)
    tol = 1e-6 * height(scans)
    enc.rotation_solver = "direct"
    ref = enc.decode(wild)
    enc.rotation_solver = "exact"
    assert np.abs(enc.decode(wild) - ref).max() < tol
    assert np.abs(np.concatenate([enc.decode(c) for c in wild]) - ref).max() < tol
    enc.rotation_solver, enc.n_jobs = "exact", 2  # threads share the pattern, one solver each
    assert np.abs(enc.decode(np.concatenate([wild, wild])) - np.concatenate([ref, ref])).max() < tol


# ``template`` is the session fixture of conftest.py (the CC0 template, cached after first use).

def pose_arm(t, x, angle, bone="upperarm01.L", axis=(0.0, 0.0, 1.0)):
    """Turn a bone's subtree by ``angle`` about ``axis`` through its head, skinned by the rig's
    weights (linear blend skinning of one joint)."""
    rig = t.rigs["default"]
    b = rig.bone_index(bone)
    sub = {b}
    for _ in range(len(rig.parents)):
        sub |= {i for i, p in enumerate(rig.parents) if p in sub}
    w = np.asarray(rig.weights[:, sorted(sub)].sum(axis=1)).ravel()
    head = rig.heads(x)[b]
    r = Rotation.from_rotvec(np.asarray(axis) * angle).as_matrix()
    return x + w[:, None] * ((x - head) @ r.T + head - x)


def young_shapes(t, n: int, rng) -> list:
    """``n`` template bodies, each a random convex mix (0.8 in all) of three 'young' macro targets."""
    young = [i for i, name in enumerate(t.target_names) if name.startswith("macrodetails/") and "young" in name]
    return [t.vertices + np.tensordot(rng.dirichlet(np.ones(3)) * 0.8, t.target_deltas[rng.choice(young, 3)], 1)
            for _ in range(n)]


def test_round_trip_on_template(template):
    t = template
    v, f = t.vertices, t.faces
    rng = np.random.default_rng(0)
    shapes = young_shapes(t, 3, rng)
    # Smooth random displacement of a shape, and an arm rotation of another.
    x0 = shapes[0] + 0.01 * np.sin(shapes[0] @ rng.normal(size=(3, 3)) * 3)
    x1 = pose_arm(t, shapes[1], 0.5)
    scans = np.stack([x0, x1, shapes[2]])
    enc = RelativeRotationEncoder(v, f).fit(scans)
    out = enc.decode(enc.encode(scans))
    assert np.abs(out - aligned(scans, enc.mean_vertices_)).max() < 1e-6 * height(scans)
