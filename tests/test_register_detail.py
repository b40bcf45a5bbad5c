"""Detail transfer (Hasler §3, end): mid-edge subdivision, normal offsets to a scan, re-added
after a morph; the detail file. Small synthetic surfaces (an icosphere of 642 vertices with a
relief of known amplitude), so the file runs in about a second; the full-body numbers are in
benchmarks/bench_detail.py and docs/registration.md."""

import numpy as np
import pytest
import trimesh

from bodyspace.errors import RegistrationError
from bodyspace.mesh.geometry import face_normals, vertex_normals
from bodyspace.mesh.topology import edges
from bodyspace.register.detail import (
    Detail,
    apply_detail,
    detail_offsets,
    faces_digest,
    load_detail,
    midpoint_subdivide,
    save_detail,
)
from bodyspace.synth.scans import sample_surface

AMPLITUDE = 0.002      # metres


def relief(x: np.ndarray) -> np.ndarray:
    """A relief of known amplitude over the unit directions of a sphere: bumps ~3 cm apart."""
    u = x / np.linalg.norm(x, axis=1, keepdims=True)
    return AMPLITUDE * np.sin(9 * u[:, 0]) * np.sin(9 * u[:, 1] + 0.5) * np.cos(7 * u[:, 2])


@pytest.fixture(scope="module")
def sphere():
    s = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    return np.asarray(s.vertices, dtype=float), np.asarray(s.faces, dtype=np.int64)


def detailed_truth(vertices, faces, base_directions, levels):
    """The true detailed surface of a body ``vertices``: subdivided, each subdivided vertex moved
    by the relief of its point on the base sphere along the body's normal there."""
    v, f = midpoint_subdivide(vertices, faces, levels)
    d, _ = midpoint_subdivide(base_directions, faces, levels)
    return v + relief(d)[:, None] * vertex_normals(v, f), f


def test_midpoint_subdivision_counts_positions_orientation(sphere):
    v, f = sphere
    e = edges(f)
    sv, sf = midpoint_subdivide(v, f, 1)
    assert sv.shape == (len(v) + len(e), 3) and sf.shape == (4 * len(f), 3)
    assert np.array_equal(sv[:len(v)], v)
    assert np.allclose(sv[len(v):], 0.5 * (v[e[:, 0]] + v[e[:, 1]]))
    # each child face lies in its parent's plane, facing the same way
    parent = np.tile(np.arange(len(f)), 4)
    assert np.all(np.einsum("fd,fd->f", face_normals(sv, sf), face_normals(v, f)[parent]) > 0.999)
    # batched and twice: the same as one at a time
    sv2, sf2 = midpoint_subdivide(np.stack([v, 2 * v]), f, 2)
    assert np.allclose(sv2[1], midpoint_subdivide(2 * v, f, 2)[0]) and len(sf2) == 16 * len(f)
    assert trimesh.Trimesh(sv2[0], sf2, process=False).is_watertight


@pytest.mark.parametrize("sigma, share", [(0.0, 0.1), (0.0005, 0.65)])
def test_detail_survives_a_morph(sphere, sigma, share):
    """The relief sampled on a dense scan of the sphere is measured to a fraction of its
    amplitude and rides on a morph (stretched, turned, moved) as the true relief does: the
    detailed morph is within ``share`` of the relief's own size of the true detailed morph
    (measured: 0.05 without noise, 0.52 with σ = 0.5 mm noise on a 0.57 mm mean relief)."""
    v, f = sphere
    true_surface, true_faces = detailed_truth(v, f, v, 2)
    rng = np.random.default_rng(0)
    points = sample_surface(true_surface, true_faces, 60_000, rng)[0] + rng.normal(0, sigma, (60_000, 3))
    detail = detail_offsets(v, f, points, levels=1)
    sv, _ = midpoint_subdivide(v, f, 1)
    h = relief(sv)
    assert detail.valid.mean() > 0.99
    err = np.abs(detail.offsets - h)[detail.valid]
    assert err.mean() < share * np.abs(h).mean(), (err.mean(), np.abs(h).mean())

    turn = trimesh.transformations.rotation_matrix(0.7, [1, 2, 0])[:3, :3]
    morphed = (v * [1.3, 0.8, 1.1]) @ turn.T + [0.5, 1.0, -0.2]
    got, got_faces = apply_detail(morphed, f, detail)
    want, _ = detailed_truth(morphed, f, v, 1)
    smooth, _ = midpoint_subdivide(morphed, f, 1)
    assert len(got_faces) == 4 * len(f)
    e_detail = np.linalg.norm(got - want, axis=1).mean()
    e_none = np.linalg.norm(smooth - want, axis=1).mean()
    assert e_detail < share * e_none, (e_detail, e_none)


def test_holes_and_far_points_keep_the_smooth_surface(sphere):
    """Where the scan has a hole the offset is marked invalid and is 0 (the fit's own surface);
    an offset larger than max_offset is not taken."""
    v, f = sphere
    rng = np.random.default_rng(1)
    points = sample_surface(v * 1.0, f, 30_000, rng)[0]
    cap = points[:, 2] > 0.07                        # a hole at the top
    detail = detail_offsets(v, f, points[~cap], levels=1)
    sv, _ = midpoint_subdivide(v, f, 1)
    top = sv[:, 2] > 0.095
    assert not detail.valid[top].any() and np.all(detail.offsets[top] == 0)
    assert detail.valid[sv[:, 2] < 0.0].all()
    # the scan 20 mm outside: beyond the 15 mm allowed, nothing is taken
    far = detail_offsets(v, f, points * 1.2, levels=1)
    assert not far.valid.any()
    with pytest.raises(RegistrationError, match="levels"):
        detail_offsets(v, f, points, levels=3)


def test_detail_file_round_trip_and_refusals(sphere, tmp_path):
    v, f = sphere
    rng = np.random.default_rng(2)
    sv, _ = midpoint_subdivide(v, f, 1)
    detail = Detail(rng.normal(0, 0.001, len(sv)), rng.random(len(sv)) > 0.1, 1, len(v), len(f),
                    faces_digest(f))
    path = save_detail(tmp_path / "detail.npz", detail, written_by="test")
    back = load_detail(path)
    assert np.allclose(back.offsets, detail.offsets, atol=1e-9) and np.array_equal(back.valid, detail.valid)
    assert (back.levels, back.n_base_vertices, back.n_base_faces) == (1, len(v), len(f))
    # another topology (or face order) is refused, naming what was expected
    with pytest.raises(RegistrationError, match="642 vertices and 1280 faces"):
        apply_detail(v, f[::-1], back, name="m.obj")
    with pytest.raises(RegistrationError, match="no such file"):
        load_detail(tmp_path / "missing.npz")
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(RegistrationError, match="could not read"):
        load_detail(tmp_path / "bad.npz")
    np.savez(tmp_path / "other.npz", header=np.frombuffer(b'{"format": "x"}', dtype=np.uint8),
             offsets=np.zeros(3), valid=np.zeros(3, bool))
    with pytest.raises(RegistrationError, match="bodyspace.Detail"):
        load_detail(tmp_path / "other.npz")


@pytest.mark.parametrize("n_points, sigma", [(4_000, 0.002), (60_000, 0.002)])
def test_detail_of_a_noisy_scan_without_relief_never_makes_the_body_worse(sphere, n_points, sigma):
    """A smooth body (no relief finer than its mesh) scanned sparsely or densely with 2 mm noise:
    every re-added millimetre would be noise or the patch's bias, so the detailed surface must be
    no farther from the truth than the smooth fit (with the James-Stein shrinkage alone, before
    the significance test: 0.21 → 0.63 mm sparse, 0.21 → 0.58 mm dense; now 0.21 both), and the
    detail says it kept little and why."""
    v, f = sphere
    rng = np.random.default_rng(3)
    points = sample_surface(v, f, n_points, rng)[0] + rng.normal(0, sigma, (n_points, 3))
    # the truth: the sphere the mesh approximates (radius 0.1 m) at every subdivided vertex
    detail = detail_offsets(v, f, points, levels=1)
    smooth, _ = midpoint_subdivide(v, f, 1)
    detailed, _ = apply_detail(v, f, detail)
    e_smooth = np.abs(np.linalg.norm(smooth, axis=1) - 0.1).mean()
    e_detail = np.abs(np.linalg.norm(detailed, axis=1) - 0.1).mean()
    assert e_detail <= e_smooth + 1e-5, (e_detail, e_smooth)
    assert detail.kept < 0.05
    note = detail.notice()
    assert note is not None and "kept" in note and "noise" in note
    assert "Notice" in detail.describe()


def test_detail_file_keeps_what_was_kept(sphere, tmp_path):
    v, f = sphere
    rng = np.random.default_rng(4)
    points = sample_surface(v, f, 4_000, rng)[0] + rng.normal(0, 0.002, (4_000, 3))
    detail = detail_offsets(v, f, points, levels=1)
    back = load_detail(save_detail(tmp_path / "d.npz", detail))
    assert back.kept == pytest.approx(detail.kept, abs=1e-5) and back.wide == pytest.approx(detail.wide, abs=1e-5)
    assert back.notice() == detail.notice()
