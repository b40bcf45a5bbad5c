"""The 3x3-block sparse Cholesky factorization (mesh.block_cholesky) against SciPy."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as sla
from _meshes import open_tube

from bodyspace.errors import MeshError
from bodyspace.mesh.block_cholesky import (
    BlockCholesky,
    BlockPattern,
    split_elimination_tree,
)
from bodyspace.mesh.topology import face_adjacency

RNG = np.random.default_rng(7)


def tube_pairs(rings=40, around=24):
    """The face-adjacency pairs (i < j) of an open tube: a pattern with a real elimination tree."""
    _, f = open_tube(rings, around, 1.0, 0.2)
    nbr = face_adjacency(f).neighbors
    i = np.broadcast_to(np.arange(len(f))[:, None], nbr.shape)
    keep = (nbr >= 0) & (i < nbr)
    return len(f), i[keep], nbr[keep]


def random_spd(n, rows, cols, rng):
    """Random off-diagonal blocks and diagonal blocks making a block-diagonally dominant SPD
    matrix; returns (diag, off, the assembled (3n, 3n) matrix)."""
    off = rng.normal(size=(len(rows), 3, 3))
    a = sp.lil_matrix((3 * n, 3 * n))
    for e, (r, c) in enumerate(zip(rows, cols)):
        a[3 * r:3 * r + 3, 3 * c:3 * c + 3] = off[e]
        a[3 * c:3 * c + 3, 3 * r:3 * r + 3] = off[e].T
    a = a.tocsr()
    row_sums = np.abs(a).sum(axis=1).A.ravel().reshape(n, 3).max(axis=1)
    g = rng.normal(size=(n, 3, 3))
    diag = (row_sums + 1.0)[:, None, None] * np.eye(3) + 0.1 * (g + np.swapaxes(g, 1, 2))
    full = a + sp.block_diag(list(diag))
    return diag, off, full.tocsc()


@pytest.mark.parametrize("lanes", [1, 2])
def test_factor_and_solve_match_scipy(lanes):
    n, rows, cols = tube_pairs()
    pattern = BlockPattern(n, rows, cols)
    chol = BlockCholesky(pattern)
    for seed in range(2):  # the same buffers refactored with new values
        diag, off, full = random_spd(n, rows, cols, np.random.default_rng(seed))
        b = RNG.normal(size=(n, 3, 3))
        chol.factor(diag, off, lanes)
        x = chol.solve(b, lanes)
        ref = sla.spsolve(full, b.reshape(3 * n, 3)).reshape(n, 3, 3)
        np.testing.assert_allclose(x, ref, rtol=0, atol=1e-10 * np.abs(ref).max())


def test_pairs_given_in_either_orientation_are_the_same_matrix():
    n, rows, cols = tube_pairs(12, 10)
    diag, off, full = random_spd(n, rows, cols, RNG)
    b = RNG.normal(size=(n, 3, 3))
    flipped = BlockCholesky(BlockPattern(n, cols, rows))  # A[c, r] = A[r, c]^T
    flipped.factor(diag, np.swapaxes(off, 1, 2))
    np.testing.assert_allclose(flipped.solve(b), sla.spsolve(full, b.reshape(-1, 3)).reshape(n, 3, 3), atol=1e-10)


def test_lanes_partition_the_elimination_tree():
    n, rows, cols = tube_pairs()
    pattern = BlockPattern(n, rows, cols)
    a, b, top = pattern.lanes
    assert len(a) and len(b)
    assert np.array_equal(np.sort(np.concatenate([a, b, top])), np.arange(n))
    parent = pattern.parent
    in_top = np.zeros(n, dtype=bool)
    in_top[top] = True
    assert np.all(in_top[parent[top][parent[top] >= 0]])  # top is closed under parents
    lane = np.full(n, 2)
    lane[a], lane[b] = 0, 1
    for j in range(n):  # no column of L links the two lanes
        rows_j = pattern.li[pattern.lp[j]:pattern.lp[j + 1]]
        if lane[j] < 2:
            assert np.all((lane[rows_j] == lane[j]) | (lane[rows_j] == 2))


def test_split_of_a_chain_and_of_two_equal_subtrees():
    # Two chains of 5 under one root (node 10): lanes are the chains, the top is the root.
    parent = np.array([1, 2, 3, 4, 10, 6, 7, 8, 9, 10, -1])
    a, b, top = split_elimination_tree(parent, np.ones(11))
    assert sorted([a.tolist(), b.tolist()]) == [[0, 1, 2, 3, 4], [5, 6, 7, 8, 9]] and top.tolist() == [10]
    # A single chain cannot be split: everything ends in the top or one lane, still a partition.
    a, b, top = split_elimination_tree(np.array([1, 2, 3, -1]), np.ones(4))
    assert sorted(np.concatenate([a, b, top]).tolist()) == [0, 1, 2, 3]


def test_not_positive_definite_names_the_block_row():
    n, rows, cols = tube_pairs(6, 8)
    diag, off, _ = random_spd(n, rows, cols, RNG)
    diag[5] = -np.eye(3)
    chol = BlockCholesky(BlockPattern(n, rows, cols))
    with pytest.raises(MeshError, match="not positive definite at block row"):
        chol.factor(diag, off)


def test_bad_patterns_and_values_are_refused():
    with pytest.raises(MeshError, match="distinct"):
        BlockPattern(4, np.array([0, 1]), np.array([0, 2]))
    with pytest.raises(MeshError, match="twice"):
        BlockPattern(4, np.array([0, 1]), np.array([1, 0]))
    with pytest.raises(MeshError, match="outside"):
        BlockPattern(4, np.array([0]), np.array([4]))
    chol = BlockCholesky(BlockPattern(4, np.array([0, 1]), np.array([1, 2])))
    with pytest.raises(MeshError, match="expected"):
        chol.factor(np.broadcast_to(np.eye(3), (4, 3, 3)), np.zeros((3, 3, 3)))
    chol.factor(np.broadcast_to(4 * np.eye(3), (4, 3, 3)), np.zeros((2, 3, 3)))
    with pytest.raises(MeshError, match="right-hand side"):
        chol.solve(np.zeros((4, 3, 2)))


@pytest.mark.parametrize("lanes", [1, 2])
def test_factor_solve_equals_factor_then_solve(lanes):
    n, rows, cols = tube_pairs()
    diag, off, full = random_spd(n, rows, cols, RNG)
    b = RNG.normal(size=(n, 3, 3))
    chol = BlockCholesky(BlockPattern(n, rows, cols))
    fused = chol.factor_solve(diag, off, b, lanes)
    np.testing.assert_allclose(fused, chol.solve(b, lanes), atol=1e-12)
    np.testing.assert_allclose(fused, sla.spsolve(full, b.reshape(-1, 3)).reshape(n, 3, 3), atol=1e-10)
