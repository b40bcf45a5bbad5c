import gzip
import shutil

import numpy as np
import pytest

from bodyspace.data import assets
from bodyspace.data.template import (
    _DAMAGED_CACHE_ERRORS,
    N_BODY_VERTICES,
    _compiled_path,
    _load_compiled,
    load_target,
    read_compiled,
    triangulate_quads,
)
from bodyspace.errors import AssetError
from bodyspace.mesh.geometry import boundary_loops, capped_volume


def test_body_only_mesh(template):
    assert template.vertices.shape == (N_BODY_VERTICES, 3)
    assert template.faces.shape == (2 * 13378, 3)
    assert template.faces.max() == N_BODY_VERTICES - 1
    h = np.ptp(template.vertices[:, 1])
    assert 1.5 < h < 1.8, "metres, +Y up"
    # The face is at the front (+Z): the nose tip is the most forward head vertex.
    head = template.vertices[template.vertices[:, 1] > template.vertices[:, 1].max() - 0.25]
    assert head[:, 2].max() > head[:, 2].mean() + 0.04


def test_triangulation_is_documented_split():
    quads = np.array([[0, 1, 2, 3], [4, 5, 6, 7]])
    np.testing.assert_array_equal(triangulate_quads(quads), [[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])


def test_closed_and_outward(template):
    assert boundary_loops(template.faces) == []
    vol = capped_volume(template.vertices, template.faces)
    assert 0.03 < vol < 0.12, "outward-facing triangles give a positive volume in m^3"


def test_mirror_and_sides(template):
    v, m = template.vertices, template.mirror
    np.testing.assert_array_equal(m[m], np.arange(len(m)))
    np.testing.assert_allclose(v[m] * [-1, 1, 1], v, atol=1e-9)
    assert (v[template.left, 0] > 0).all() and (v[template.right, 0] < 0).all()
    assert len(template.left) == len(template.right)


def test_joints_inside_body_and_symmetric(template):
    J = template.joints(template.vertices)
    names = template.joint_names
    lo, hi = template.vertices.min(0), template.vertices.max(0)
    assert ((J >= lo - 1e-9) & (J <= hi + 1e-9)).all()
    knee_l, knee_r = J[names.index("joint-l-knee")], J[names.index("joint-r-knee")]
    np.testing.assert_allclose(knee_l * [-1, 1, 1], knee_r, atol=2e-3)
    assert J[names.index("joint-head")][1] > J[names.index("joint-neck")][1] > J[names.index("joint-pelvis")][1]
    assert J[names.index("joint-pelvis")][1] > knee_l[1] > J[names.index("joint-l-ankle")][1]


def test_rigs_weights_on_body(template):
    for name, rig in template.rigs.items():
        W = rig.weights
        assert W.shape == (N_BODY_VERTICES, rig.n_bones)
        np.testing.assert_allclose(np.asarray(W.sum(axis=1)).ravel(), 1.0, atol=1e-9)
        assert (rig.parents < np.arange(rig.n_bones)).all() or (rig.parents == -1).sum() >= 1
        heads = rig.heads(template.vertices)
        assert np.isfinite(heads).all()
    assert template.rigs["default"].n_bones == 163


def test_joint_regressor_batches(template, phenotype_model):
    V = phenotype_model.vertices({"gender": np.array([0.0, 1.0])})
    J = template.joints(V)
    np.testing.assert_allclose(J[1], template.joints(V[1]))


def _cache_copy(tmp_path, monkeypatch):
    """A private cache holding a copy of the real compiled template (same asset root, same key)."""
    root = assets.asset_root().resolve()
    real = _compiled_path(root)
    monkeypatch.setenv("BODYSPACE_ASSETS", str(root))
    monkeypatch.setenv("BODYSPACE_CACHE", str(tmp_path / "cache"))
    copy = _compiled_path(root)
    assert copy != real and copy.name == real.name
    copy.parent.mkdir(parents=True)
    shutil.copyfile(real, copy)
    return root, copy


@pytest.mark.parametrize("fraction", [0.0, 0.5])
def test_damaged_compiled_cache_is_detected(template, tmp_path, monkeypatch, fraction):
    _, copy = _cache_copy(tmp_path, monkeypatch)
    assert read_compiled(copy).faces.shape == template.faces.shape
    data = copy.read_bytes()
    copy.write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises(_DAMAGED_CACHE_ERRORS):
        read_compiled(copy)


def test_truncated_compiled_cache_heals(template, tmp_path, monkeypatch):
    """A cache cut short (a killed run, a full disk) is rebuilt, not reported on every later run."""
    root, copy = _cache_copy(tmp_path, monkeypatch)
    data = copy.read_bytes()
    copy.write_bytes(data[: len(data) // 3])
    healed = _load_compiled.__wrapped__(root)  # the uncached function: the lru_cache stays untouched
    np.testing.assert_array_equal(healed.faces, template.faces)
    np.testing.assert_allclose(healed.vertices, template.vertices)
    np.testing.assert_array_equal(read_compiled(copy).faces, template.faces)  # the file itself is whole again


def test_target_rows_parse_exactly_and_a_short_row_is_refused(tmp_path):
    """MakeHuman target rows (index dx dy dz, decimetres, comments) → metres; a row of three numbers
    is an error naming the file, never a shifted read."""
    good = tmp_path / "a.target.gz"
    good.write_bytes(gzip.compress(b"# comment\n3 .001 0 -.5\n\n0 1e-3 2 3\n"))
    out = load_target(good, 5)
    np.testing.assert_allclose(out[3], [0.0001, 0.0, -0.05])
    np.testing.assert_allclose(out[0], [0.0001, 0.2, 0.3])
    assert not out[[1, 2, 4]].any()
    bad = tmp_path / "b.target.gz"
    bad.write_bytes(gzip.compress(b"3 .001 0\n0 1 2 3\n"))
    with pytest.raises(AssetError, match="b.target.gz"):
        load_target(bad, 5)
    worse = tmp_path / "c.target.gz"
    worse.write_bytes(gzip.compress(b"3 .001 x 4\n"))
    with pytest.raises(AssetError, match="c.target.gz"):
        load_target(worse, 5)
