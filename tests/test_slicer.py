"""The compiled part-girth slicer (issue 16, ``slicing.part_girths``) against the numpy path it
replaced (``part_sections`` + ``support_perimeters`` + ``contour_girths``, kept for drawn
polylines): the same girths on library poses, on a foreign topology and at the edges (a plane
off the part, a band whose planes leave the part, collinear and repeated points)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bodyspace.measure import evaluate, load_landmarks, load_measurement_set
from bodyspace.measure.definitions import with_landmarks, with_vertex_parts
from bodyspace.measure.methods import Topology
from bodyspace.measure.parts import parts_from_landmarks
from bodyspace.measure.slicing import (
    MODE_MAX,
    MODE_MIN,
    MODE_ONE,
    _hull_chain,
    part_fronts,
    hull_perimeter,
    part_girths,
    part_mesh,
    part_sections,
)
from bodyspace.rig.posing import pose_bodies
from bodyspace.synth.foreign import foreign_topology, transfer
from bodyspace.synth.phenotype import PARAMETERS
from bodyspace.synth.poses import load_pose_library

POSES = ("rest", "arms_crossed", "squat", "hands_on_hips", "look_down", "t_pose")
TOL = 1e-5          # 0.01 mm


@pytest.fixture(scope="module")
def mset():
    return load_measurement_set()


@pytest.fixture(scope="module")
def bodies(template, phenotype_model):
    """Three phenotypes, each standing and in the library poses (as posed: the tape meets arms,
    bent legs and a bowed head)."""
    rng = np.random.default_rng(5)
    phen = rng.uniform(0.2, 0.8, size=(3, len(PARAMETERS)))
    phen[:, PARAMETERS.index("age")] = 0.6                                      # adults
    rest = phenotype_model.vertices(phen)
    rig = template.rigs["default"]
    R = load_pose_library().stack(list(POSES), rig)
    return np.concatenate([pose_bodies(np.repeat(b[None], len(POSES), 0), rig, R, on_ground=True) for b in rest])


def _slices(mset):
    return [m["name"] for m in mset.measurements if m["method"] == "slice"]


def _same(mset, vertices, faces, names):
    """The compiled path (no polylines) and the numpy path (polylines kept) give the same values."""
    fast = evaluate(mset, vertices, faces, check_scale=False)
    ref = evaluate(mset, vertices, faces, keep_polylines=True, check_scale=False)
    for name in names:
        a, b = np.atleast_1d(fast[name].value), np.atleast_1d(ref[name].value)
        assert (np.isnan(a) == np.isnan(b)).all(), name
        assert np.nanmax(np.abs(a - b), initial=0.0) <= TOL, (name, np.nanmax(np.abs(a - b)))
        assert fast[name].note == ref[name].note, name
    return fast


def test_same_girths_as_the_numpy_path_on_library_poses(mset, bodies, template):
    fast = _same(mset, bodies, template.faces, _slices(mset))
    assert np.isfinite(fast["chest_girth"].value).sum() >= len(bodies) - 3     # real girths, not all NaN


def test_same_girths_on_a_foreign_topology(mset, bodies, template, tmp_path):
    """Remeshed and reordered: its parts come from the landmark skeleton, its edges are others."""
    topo = foreign_topology(template, 4000, rng=2, mset=mset)
    path = tmp_path / "landmarks.json"
    path.write_text(json.dumps(topo.landmark_file()))
    lms, nv = load_landmarks(path)
    fset = with_landmarks(mset, lms, nv, str(path))
    moved = transfer(topo.correspondence, template.faces, bodies[::2])
    P = fset.landmark_matrix(nv) @ moved[0]
    fset = with_vertex_parts(fset, parts_from_landmarks(moved[0], {n: P[i] for i, n in enumerate(fset.landmarks)}))
    _same(fset, moved, topo.faces, _slices(fset))


def _reference(v, edges, border, origins, normal, mode):
    """``methods.slice_girth``'s numpy steps for a part: girth (N,), missed (N,)."""
    from bodyspace.measure.slicing import contour_girths, support_perimeters

    P, n = origins.shape[:2]
    cuts, edge = part_sections(v, edges, origins, normal)
    chosen = np.where(np.bincount(cuts.body, minlength=P * n) >= 3, np.arange(P * n), -1)
    opened = np.bincount(cuts.body[border[edge]], minlength=P * n) > 0
    missed = (chosen < 0).reshape(P, n).all(axis=0)
    normals = np.tile(normal, (P, 1))
    if P == 1:
        k = np.zeros(n, dtype=np.int64)
    else:
        est = support_perimeters(cuts, chosen, normals).reshape(P, n)
        if mode == MODE_MIN:
            whole = ~opened.reshape(P, n)
            est = np.where(whole | ~whole.any(axis=0), est, np.nan)
        est = np.where(np.isnan(est), -np.inf if mode == MODE_MAX else np.inf, est)
        k = np.argmax(est, axis=0) if mode == MODE_MAX else np.argmin(est, axis=0)
    group = k * n + np.arange(n)
    ch = np.full(P * n, -1, dtype=np.int64)
    ch[group] = chosen[group]
    return contour_girths(cuts, ch, normals)[0][group], missed


@pytest.mark.parametrize("mode", [MODE_MAX, MODE_MIN])
def test_bands_that_leave_the_part_and_planes_off_it(mset, bodies, template, mode):
    """A band along the whole body through the torso: its planes above the shoulders and below the
    crotch leave the torso or miss it (NaN, ``missed``), its min must skip the opened planes."""
    topo = Topology(template.faces)
    edges, border = topo.part_edges(mset.vertex_parts, "torso")
    v = bodies[:4]
    normal = np.tile([0.0, 1.0, 0.0], (len(v), 1))
    lo, hi = v[:, :, 1].min(1), v[:, :, 1].max(1)
    t = np.linspace(-0.1, 1.1, 15)[:, None]
    origins = np.zeros((15, len(v), 3))
    origins[..., 1] = lo + t * (hi - lo)
    g, plane, missed = part_girths(v, part_mesh(edges, border), origins, normal, mode)
    ref, ref_missed = _reference(v, edges, border, origins, normal, mode)
    np.testing.assert_allclose(g, ref, atol=TOL)
    assert (missed == ref_missed).all() and not missed.any()
    # Every plane above the head: all miss.
    above = origins[-2:].copy()
    above[..., 1] = hi + 0.1
    g, _, missed = part_girths(v, part_mesh(edges, border), above, normal, mode)
    assert missed.all() and np.isnan(g).all()
    # One plane through the waist (MODE_ONE).
    g, plane, _ = part_girths(v, part_mesh(edges, border), origins[7:8], normal, MODE_ONE)
    np.testing.assert_allclose(g, _reference(v, edges, border, origins[7:8], normal, MODE_ONE)[0], atol=TOL)
    assert (plane == 0).all() and (g > 0.5).all()


def test_hull_of_degenerate_points():
    """Collinear points (a tape doubled back: twice the length), repeats, three points, a square
    with points on its sides: the chain's hull perimeter is the Qhull/monotone-chain one."""
    rng = np.random.default_rng(0)
    cases = [np.c_[np.linspace(0, 1, 7), np.linspace(0, 2, 7)],
             np.repeat(rng.normal(size=(5, 2)), 3, axis=0),
             rng.normal(size=(3, 2)),
             np.array([[0, 0], [1, 0], [1, 1], [0, 1], [0.5, 0], [1, 0.5], [0.5, 0.5], [0, 0]], float),
             rng.normal(size=(200, 2))]
    for xy in cases:
        k = len(xy)
        order, hull = np.empty(k, np.int64), np.empty(k + 1, np.int64)
        m = _hull_chain(np.ascontiguousarray(xy[:, 0]), np.ascontiguousarray(xy[:, 1]), k, order, hull)
        h = xy[hull[:m]]
        per = np.linalg.norm(h - np.roll(h, -1, axis=0), axis=1).sum() if m > 1 else 0.0
        assert per == pytest.approx(hull_perimeter(xy)[0], abs=1e-12), xy


def test_unpose_known_in_place_and_per_body_heads(template, bodies):
    """The chunk's bodies turn different bones (standing ones none): each solves its own turned
    bones' heads; in place gives the same rest bodies, and a non-float64 array is refused."""
    from bodyspace.errors import ParameterError
    from bodyspace.rig.unpose import unpose_known

    rig = template.rigs["default"]
    R = np.concatenate([load_pose_library().stack(list(POSES), rig)] * 3)
    rest, _, info = unpose_known(bodies, rig, R)
    assert (info.shape_distance_m < 1e-5).all()
    standing = bodies[::len(POSES)]                                        # pose "rest" of each phenotype
    for k in range(len(POSES)):
        np.testing.assert_allclose(rest[k::len(POSES)], standing, atol=1e-6)
    work = bodies.copy()
    again = unpose_known(work, rig, R, in_place=True)[0]
    assert again is work and np.abs(again - rest).max() == 0.0
    with pytest.raises(ParameterError, match="in_place"):
        unpose_known(bodies.astype(np.float32), rig, R, in_place=True)


def test_read_rows_into_a_kept_array(tmp_path):
    """``measure DB`` reads each chunk into arrays it keeps: the same rows as a fresh read; an
    array of another shape or dtype is refused with both named."""
    from bodyspace.errors import DatabaseError
    from bodyspace.rowfile import read_rows

    data = np.arange(5 * 4 * 3, dtype=np.float32).reshape(5, 4, 3)
    path = tmp_path / "rows.npy"
    np.save(path, data)
    keep = np.empty((3, 4, 3), np.float32)
    got = read_rows(path, 1, 4, out=keep)
    assert got is keep and np.array_equal(got, data[1:4])
    with pytest.raises(DatabaseError, match=r"\(2, 4, 3\) float32.*\(3, 4, 3\) float64"):
        read_rows(path, 3, 5, out=np.empty((3, 4, 3)))


def _tube(n_around=24, n_rings=11, dz=0.01):
    """A tube narrowing upwards (radius 6 cm at the bottom, 5 cm at the top), open at both ends:
    vertices (1, V, 3), faces (F, 3) (each quad two triangles, one diagonal per quad)."""
    z = np.arange(n_rings) * dz
    r = 0.06 - 0.1 * z
    th = 2 * np.pi * np.arange(n_around) / n_around
    v = np.stack([np.repeat(r, n_around) * np.tile(np.cos(th), n_rings), np.repeat(z, n_around),
                  np.repeat(r, n_around) * np.tile(np.sin(th), n_rings)], axis=1)
    idx = np.arange(n_rings * n_around).reshape(n_rings, n_around)
    a, b = idx[:-1], np.roll(idx[:-1], -1, axis=1)
    c, d = idx[1:], np.roll(idx[1:], -1, axis=1)
    faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    return v[None], faces


def test_a_plane_grazing_one_triangle_of_another_part_does_not_flip_the_min():
    """Issue 15: the neck's min band left out every plane that touched one edge of a triangle with
    a head vertex, so one vertex decided between planes centimetres apart in girth (ISO study:
    -124 and +47 mm on two scans). A tube whose top rings are another part, and one vertex of the
    ring below them too: the band's top plane grazes that vertex's triangles. Its ring goes on
    round them and back onto the part, so it is measured as the tape's ring: the same girth and
    plane as without the stray vertex; a ring that does not come back (a hole in the mesh) still
    leaves the plane out of the min."""
    from bodyspace.measure.slicing import mesh_edges, plane_basis, ring_runs

    v, faces = _tube()
    on = v[0, :, 1] < 0.075                                      # rings 0-7 the part, 8-10 another
    origins = np.zeros((7, 1, 3))
    origins[:, 0, 1] = 0.005 + 0.01 * np.arange(7)               # between the rings, the top at 6.5 cm
    normal = np.array([[0.0, 1.0, 0.0]])
    g_clean, plane_clean, _ = _tube_girths(v, faces, on, origins, normal)[:3]
    assert plane_clean[0] == 6                                   # the narrowest plane of the band
    stray = on.copy()
    stray[7 * 24] = False                                        # a vertex of ring 7 is the other part's
    g, plane, missed, pm = _tube_girths(v, faces, stray, origins, normal)
    assert plane[0] == 6 and not missed[0]
    assert g[0] == pytest.approx(g_clean[0], abs=1e-12)
    assert g[0] == pytest.approx(2 * np.pi * 0.0535, rel=0.01)  # the tube's circumference there
    # The rule it replaces (any crossing of the border opens the plane): the plane below, wider.
    g_old, plane_old, _ = part_girths(v, part_mesh(pm.edges[pm.gid], pm.border), origins, normal, MODE_MIN)
    assert plane_old[0] == 5 and g_old[0] - g[0] > 0.005
    # The numpy path's runs (``ring_runs``): the part's crossings plus them are the kernel's ring.
    cuts, _ = part_sections(v, pm.edges[pm.gid], origins, normal)
    pts, group, closed = ring_runs(v, pm, origins, normal)
    assert closed.all() and set(group) == {6} and len(pts) == 2  # the two crossings off the part
    u, w = plane_basis(normal)
    ring = np.concatenate([cuts.points[cuts.body == 6], pts])
    assert hull_perimeter(np.stack([ring @ u[0], ring @ w[0]], axis=1))[0] == pytest.approx(g[0], abs=1e-12)
    # A hole beside the stray vertex: the ring leaves the part and does not come back, so the
    # plane stays out of the min (the plane below is chosen, as before).
    holed = faces[~(np.sort(faces, axis=1) == [6 * 24, 7 * 24, 7 * 24 + 1]).all(axis=1)]
    assert len(holed) == len(faces) - 1 and (mesh_edges(holed)[1] < 0).any()
    g_h, plane_h, _, pm_h = _tube_girths(v, holed, stray, origins, normal)
    assert plane_h[0] == 5 and not ring_runs(v, pm_h, origins, normal)[2][6]


def _tube_girths(v, faces, on, origins, normal):
    """``part_girths`` of a min band round the vertices ``on`` (V,) bool, walking the whole mesh
    (as ``Topology.part_mesh`` builds it): girth, plane, missed, the ``PartMesh``."""
    from bodyspace.measure.slicing import face_edge_ids, mesh_edges

    edges, edge_faces = mesh_edges(faces)
    keep = on[edges].all(axis=1)
    face_on = on[faces].all(axis=1)
    ef = edge_faces[keep]
    border = ~np.where(ef >= 0, face_on[np.maximum(ef, 0)], False).all(axis=1)
    mesh = {"faces": faces, "edges": edges, "edge_faces": edge_faces, "face_edges": face_edge_ids(faces, edges),
            "gid": np.flatnonzero(keep), "on": on}
    pm = part_mesh(edges[keep], border, mesh=mesh)
    return (*part_girths(v, pm, origins, normal, MODE_MIN), pm)


def test_part_fronts_are_the_crossings_front(mset, bodies, template):
    """``part_fronts`` (the fold band's compiled pass): each plane's front is the largest forward
    coordinate of its crossings with the part (``part_sections``' points), the hull plane's girth
    is ``part_girths``' of that plane alone, and a body left out gets NaN."""
    topo = Topology(template.faces)
    edges, border = topo.part_edges(mset.vertex_parts, "torso")
    v = bodies[::len(POSES)]                                                  # the three standing
    normal = np.tile([0.0, 1.0, 0.0], (len(v), 1))
    forward = np.tile([0.0, 0.0, 1.0], (len(v), 1))
    lo, hi = v[:, :, 1].min(1), v[:, :, 1].max(1)
    origins = np.zeros((9, len(v), 3))
    origins[..., 1] = lo + np.linspace(0.72, 0.55, 9)[:, None] * (hi - lo)     # chest down to the waist
    mesh = part_mesh(edges, border)
    active = np.array([True, False, True])
    fronts, girth, _ = part_fronts(v, mesh, origins, normal, forward, hull_plane=4, active=active)
    cuts, _ = part_sections(v, edges, origins, normal)
    want = np.full(len(origins) * len(v), -np.inf)
    np.maximum.at(want, cuts.body, cuts.points[:, 2])
    want = want.reshape(len(origins), len(v))
    np.testing.assert_allclose(fronts[:, active], want[:, active], atol=1e-12)
    assert np.isnan(fronts[:, ~active]).all() and np.isnan(girth[~active]).all()
    one = part_girths(v, mesh, origins[4:5], normal, MODE_ONE)[0]
    np.testing.assert_array_equal(girth[active], one[active])
