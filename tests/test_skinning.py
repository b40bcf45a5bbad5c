"""Tests for bodyspace.rig.skinning: compiled LBS/DQS against the numpy reference, compiled FK."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

try:
    import bodyspace  # noqa: F401
except ModuleNotFoundError:  # not installed: run from the source tree
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from bodyspace.errors import MeshError, ParameterError
from bodyspace.rig.kinematics import (
    dual_quaternion_skinning_numpy,
    forward_kinematics,
    forward_kinematics_numpy,
    linear_blend_skinning_numpy,
    rotvec_to_matrix,
)
from bodyspace.rig import skinning
from bodyspace.rig.skinning import FRAME_BLOCK, dual_quaternion_skinning, linear_blend_skinning

SKINNERS = [(linear_blend_skinning, linear_blend_skinning_numpy), (dual_quaternion_skinning, dual_quaternion_skinning_numpy)]


def random_weights(rng, V, B, max_influences=9):
    """Sparse (V, B) rows of 1..max_influences random positive weights summing to one; a few
    rows with more than four bones, so the padded second pass of the kernels runs."""
    rows, cols, vals = [], [], []
    for i in range(V):
        k = int(rng.integers(1, max_influences + 1))
        bones = rng.choice(B, size=min(k, B), replace=False)
        w = rng.uniform(0.05, 1.0, len(bones))
        rows += [i] * len(bones)
        cols += list(bones)
        vals += list(w / w.sum())
    return sp.csr_matrix((vals, (rows, cols)), shape=(V, B))


def random_rigid(rng, N, B, scale=1.0):
    G = np.tile(np.eye(4), (N, B, 1, 1))
    G[..., :3, :3] = rotvec_to_matrix(rng.normal(size=(N, B, 3)) * scale)
    G[..., :3, 3] = rng.normal(size=(N, B, 3))
    return G


@pytest.mark.parametrize("compiled, reference", SKINNERS)
@pytest.mark.parametrize("N", [1, 3, FRAME_BLOCK + 5])
def test_kernels_equal_the_numpy_reference(compiled, reference, N):
    rng = np.random.default_rng(N)
    V, B = 123, 11          # full vertex tiles (8 float64, 16 float32 lanes) and a partial one
    W = random_weights(rng, V, B)
    G = random_rigid(rng, N, B, scale=1.5)
    per_body = rng.normal(size=(N, V, 3))
    shared = rng.normal(size=(V, 3))
    for rest in (per_body, shared):
        ref = reference(rest, W, G)
        scale = np.abs(ref).max()
        for lanes in (1, 2):
            got = compiled(rest, W, G, lanes=lanes)
            assert got.dtype == np.float64 and got.shape == (N, V, 3)
            assert np.abs(got - ref).max() <= 1e-12 * scale
        got32 = compiled(rest, W, G, dtype=np.float32)
        assert got32.dtype == np.float32
        assert np.abs(got32 - ref).max() <= 1e-6 * scale
    # dense weights and a broadcast (stride 0) batch of one body are the same inputs
    np.testing.assert_allclose(compiled(np.broadcast_to(shared, (N, V, 3)), W.toarray(), G),
                               reference(shared, W, G), rtol=0, atol=1e-12 * scale)


@pytest.mark.parametrize("compiled, reference", SKINNERS)
def test_identity_pose_returns_the_input_bit_for_bit(compiled, reference):
    rng = np.random.default_rng(5)
    V, B, N = 70, 6, 4
    W = random_weights(rng, V, B)
    rest = rng.normal(size=(N, V, 3))
    identity = np.tile(np.eye(4), (N, B, 1, 1))
    np.testing.assert_array_equal(compiled(rest, W, identity), rest)
    np.testing.assert_array_equal(compiled(rest[0], W, identity), np.broadcast_to(rest[0], (N, V, 3)))
    # float32 arithmetic: the input rounded to float32, bit for bit
    np.testing.assert_array_equal(compiled(rest, W, identity, dtype=np.float32), rest.astype(np.float32))


@pytest.mark.parametrize("compiled, reference", SKINNERS)
def test_float32_arithmetic_error_on_a_body_scale_mesh(compiled, reference):
    """float32 output is computed in float32 (tables, blend, apply): the error against the
    float64 reference stays within a few float32 roundings of a 1 m body (1 ulp: 0.06 um)."""
    rng = np.random.default_rng(11)
    V, B, N = 200, 9, FRAME_BLOCK + 3
    W = random_weights(rng, V, B, max_influences=5)
    G = random_rigid(rng, N, B, scale=1.0)
    G[..., :3, 3] *= 0.5                                  # metres, a body's bone offsets
    rest = rng.uniform(-1.0, 1.0, size=(V, 3))
    ref = reference(rest, W, G)
    got = compiled(rest, W, G, dtype=np.float32)
    assert np.abs(got - ref).max() < 2e-6                 # metres: 0.002 mm
    assert np.abs(got - ref).max() > 0                    # (float32 arithmetic, not a rounded float64 result)


@pytest.mark.parametrize("compiled, reference", SKINNERS)
def test_streaming_stores_write_the_same(compiled, reference, monkeypatch):
    """Outputs past STREAM_MIN_BYTES go out through staged runs and non-temporal stores (whole
    aligned lines streamed, partial ones stored plainly): same values, every alignment of a row."""
    rng = np.random.default_rng(13)
    V, B, N = 301, 7, 45                     # rows of 903 values: each frame's run starts at another offset
    W = random_weights(rng, V, B)
    G = random_rigid(rng, N, B)
    rest = rng.normal(size=(N, V, 3))
    plain = {dt: compiled(rest, W, G, dtype=dt, lanes=1) for dt in (np.float64, np.float32)}
    monkeypatch.setattr(skinning, "STREAM_MIN_BYTES", 0)
    for dt, expected in plain.items():
        for lanes in (1, 2):
            np.testing.assert_array_equal(compiled(rest, W, G, dtype=dt, lanes=lanes), expected)
    np.testing.assert_allclose(plain[np.float64], reference(rest, W, G), rtol=0, atol=1e-12 * np.abs(rest).max() * 10)


@pytest.mark.parametrize("compiled", [linear_blend_skinning, dual_quaternion_skinning])
def test_non_contiguous_out_is_written(compiled):
    rng = np.random.default_rng(12)
    V, B, N = 37, 5, 6
    W = random_weights(rng, V, B)
    G = random_rigid(rng, N, B)
    rest = rng.normal(size=(N, V, 3))
    base = np.zeros((V, N, 3))
    out = base.transpose(1, 0, 2)                         # (N, V, 3) view, not C-contiguous
    assert compiled(rest, W, G, out=out) is out
    np.testing.assert_array_equal(out, compiled(rest, W, G))


def test_dqs_hemisphere_flip():
    """A bone's quaternion given with the opposite sign (-q is the same rotation) blends the same:
    without the flip into the pivot's hemisphere the two would cancel and the vertex collapse."""
    rng = np.random.default_rng(6)
    V, B, N = 30, 2, 1
    W = sp.csr_matrix(np.column_stack([np.full(V, 0.6), np.full(V, 0.4)]))
    G = random_rigid(rng, N, B, scale=0.3)
    G[0, 1, :3, :3] = rotvec_to_matrix(np.array([0.0, 2.9, 0.0]))     # near pi: q_w small, sign flips easily
    G[0, 0, :3, :3] = rotvec_to_matrix(np.array([0.0, -2.9, 0.0]))
    rest = rng.normal(size=(V, 3))
    got = dual_quaternion_skinning(rest, W, G)
    np.testing.assert_allclose(got, dual_quaternion_skinning_numpy(rest, W, G), atol=1e-12)
    # rigid per vertex: distances between points skinned alike are kept
    d0 = np.linalg.norm(rest[1:] - rest[:1], axis=1)
    d1 = np.linalg.norm(got[0, 1:] - got[0, :1], axis=1)
    np.testing.assert_allclose(d1, d0, atol=1e-12)


@pytest.mark.parametrize("compiled", [linear_blend_skinning, dual_quaternion_skinning])
def test_out_argument_and_memmap(compiled, tmp_path):
    rng = np.random.default_rng(7)
    V, B, N = 50, 5, 9
    W = random_weights(rng, V, B)
    G = random_rigid(rng, N, B)
    rest = rng.normal(size=(V, 3))
    expected = compiled(rest, W, G)
    out = np.full((N, V, 3), np.nan)
    assert compiled(rest, W, G, out=out) is out
    np.testing.assert_array_equal(out, expected)
    mm = np.lib.format.open_memmap(tmp_path / "posed.npy", mode="w+", dtype=np.float32, shape=(N, V, 3))
    compiled(rest, W, G, out=mm)
    mm.flush()
    np.testing.assert_allclose(np.load(tmp_path / "posed.npy"), expected, atol=1e-6)
    with pytest.raises(ParameterError, match="out"):
        compiled(rest, W, G, out=np.empty((N, V + 1, 3)))
    with pytest.raises(ParameterError, match="out"):
        compiled(rest, W, G, out=np.empty((N, V, 3), dtype=np.int32))


@pytest.mark.parametrize("compiled", [linear_blend_skinning, dual_quaternion_skinning])
def test_bad_inputs_raise_clear_errors(compiled):
    rng = np.random.default_rng(8)
    V, B, N = 20, 4, 2
    W = random_weights(rng, V, B, max_influences=3)
    G = random_rigid(rng, N, B)
    rest = rng.normal(size=(V, 3))
    with pytest.raises(ParameterError, match=r"weights: shape \(20, 3\), expected \(20, 4\)"):
        compiled(rest, W[:, :3], G)
    with pytest.raises(MeshError, match="vertices"):
        compiled(rng.normal(size=(3, V, 3)), W, G)
    with pytest.raises(MeshError, match="vertices"):
        compiled(rng.normal(size=(V, 2)), W, G)
    with pytest.raises(ParameterError, match="transforms"):
        compiled(rest, W, G[..., :3, :])
    unnormalized = W.multiply(1.5).tocsr()
    with pytest.raises(ParameterError, match=r"row 0 \(vertex 0\) sums to 1.5.*normalize"):
        compiled(rest, unnormalized, G)
    empty_row = W.tolil()
    empty_row[7, :] = 0
    with pytest.raises(ParameterError, match=r"row 7 \(vertex 7\) sums to 0"):
        compiled(rest, empty_row.tocsr(), G)
    nan_w = W.copy()
    nan_w.data[nan_w.indptr[5]] = np.nan
    with pytest.raises(ParameterError, match=r"row 5 .*NaN"):
        compiled(rest, nan_w, G)
    nan_g = G.copy()
    nan_g[1, 2, 0, 3] = np.nan
    with pytest.raises(ParameterError, match="transforms: NaN"):
        compiled(rest, W, nan_g)
    for shape in [(V, 3), (N, V, 3)]:
        bad = rng.normal(size=shape)
        bad[(0,) * (len(shape) - 2) + (11, 1)] = np.inf
        with pytest.raises(MeshError, match="NaN or infinity"):
            compiled(bad, W, G)
    with pytest.raises(ParameterError, match="dtype"):
        compiled(rest, W, G, dtype=np.int64)
    with pytest.raises(ParameterError, match="lanes"):
        compiled(rest, W, G, lanes=3)


def test_compiled_forward_kinematics_equals_numpy():
    rng = np.random.default_rng(9)
    N, B = 5, 17
    parents = np.array([-1] + [int(rng.integers(0, b)) for b in range(1, B)])
    perm = rng.permutation(B)                       # children listed before parents too
    inv = np.argsort(perm)
    parents = np.where(parents[perm] < 0, -1, inv[np.maximum(parents[perm], 0)])
    R = rotvec_to_matrix(rng.normal(size=(N, B, 3)))
    for heads in (rng.normal(size=(B, 3)), rng.normal(size=(N, B, 3))):
        for translation in (None, rng.normal(size=(N, 3))):
            np.testing.assert_allclose(forward_kinematics(R, heads, parents, translation),
                                       forward_kinematics_numpy(R, heads, parents, translation), atol=1e-13)
    with pytest.raises(ParameterError, match="heads"):
        forward_kinematics(R, rng.normal(size=(2, B, 3)), parents)
    with pytest.raises(ParameterError, match="parents"):
        forward_kinematics(R, rng.normal(size=(B, 3)), parents[:-1])
