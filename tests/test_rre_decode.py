"""Decoding of modified RRE codes on the 13,380-vertex template: the per-body block Cholesky
factorization of Eq. 9 (``FixedPatternRotationSolver``) against the SuperLU baseline."""

import numpy as np
import pytest
from test_encoding import aligned, height, pose_arm, young_shapes

from bodyspace.encoding import RelativeRotationEncoder
from bodyspace.shape import ShapeSpace


@pytest.fixture(scope="module")
def coded(template):
    """An encoder fitted on a small posed population of the template, its codes and scans."""
    t = template
    v, f = t.vertices, t.faces
    shapes = young_shapes(t, 4, np.random.default_rng(3))
    posed = [pose_arm(t, shapes[0], 1.1), pose_arm(t, shapes[1], -0.9, axis=(1.0, 0.0, 0.0)),
             pose_arm(t, shapes[2], 0.8, bone="upperarm01.R"), pose_arm(t, shapes[3], 1.3, bone="upperarm01.R")]
    scans = np.stack(shapes + posed)
    # Linear blend skinning folds a few triangles at large angles: accept them, as the benchmark does.
    enc = RelativeRotationEncoder(v, f, on_flipped="ignore").fit(scans)
    return enc, enc.encode(scans), scans


def modified_codes(enc, codes):
    """Halfway codes (rest -> posed, same subject) and 2-sigma PCA samples of the shape-only and
    the pose+shape model."""
    halfway = 0.5 * (codes[:4] + codes[4:])
    shape_only = ShapeSpace(enc, n_components=3).fit(codes[:4])
    both = ShapeSpace(enc, n_components=7).fit(codes)
    return {"halfway": halfway,
            "shape-only": shape_only.inverse_transform(shape_only.sample_coefficients(3, sigma_range=2.0, rng=0)),
            "pose+shape": both.inverse_transform(both.sample_coefficients(3, sigma_range=2.0, rng=0))}


def test_decode_matches_the_superlu_baseline_on_modified_codes(coded):
    """One body at a time (two lanes) and a batch (a body per thread) both equal the baseline
    that assembles and factors the whole system with SuperLU, to round-off."""
    enc, codes, scans = coded
    for name, c in modified_codes(enc, codes).items():
        enc.rotation_solver = "direct"
        ref = enc.decode(c)
        enc.rotation_solver = "exact"
        one = np.concatenate([enc.decode(row) for row in c])
        assert enc.last_factorized_ == 1
        batch = enc.decode(c)
        assert enc.last_factorized_ == len(c)
        assert np.abs(one - ref).max() < 1e-9, name
        assert np.abs(batch - ref).max() < 1e-9, name
    # Round trips: consistent codes, solved by the tree rotations without a factorization.
    out = enc.decode(codes)
    assert enc.last_factorized_ == 0
    assert np.abs(out - aligned(scans, enc.mean_vertices_)).max() < 1e-6 * height(scans)


def test_solve_rotations_in_mesh_order(coded):
    """``solve_rotations`` (mesh face order in and out) agrees between the exact path, which
    works in the graph's own face order, and the baseline."""
    enc, codes, _ = coded
    rel = enc.relative_rotations(modified_codes(enc, codes)["pose+shape"][:2])
    exact = enc.solve_rotations(rel, "exact")
    assert enc.last_factorized_ == 2
    np.testing.assert_allclose(exact, enc.solve_rotations(rel, "direct"), atol=1e-9)
