"""Tests for bodyspace.report.render: projection, shading, drawing and atomic PNG output."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.image import imread

try:
    import bodyspace  # noqa: F401
except ModuleNotFoundError:  # not installed: run from the source tree
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from bodyspace.errors import MeshError, ParameterError
from bodyspace.mesh.geometry import vertex_normals as mesh_normals
from bodyspace.report import render as R
from bodyspace.report.rig_figure import weight_view

# ------------------------------------------------------------------------------------ helpers

def sphere(radius=1.0, center=(0.0, 0.0, 0.0), subdivisions=3):
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return m.vertices + np.asarray(center), m.faces


def ellipsoid(axes=(0.4, 0.9, 0.15)):
    v, f = sphere(1.0, subdivisions=3)
    return v * np.asarray(axes), f


def upright_capsule(height, radius=0.15):
    """A capsule of total ``height`` standing on y=0 (trimesh builds it along Z)."""
    m = trimesh.creation.capsule(height=height - 2 * radius, radius=radius, count=[24, 24])
    # Rotation of -90° about X (Z → Y), a proper rotation so the faces stay outward.
    v = m.vertices[:, [0, 2, 1]] * np.array([1.0, 1.0, -1.0])
    v[:, 1] -= v[:, 1].min()
    return v, m.faces


def render_ax(draw, xlim=(-1.2, 1.2), ylim=(-1.2, 1.2), size=(240, 240)):
    """Call ``draw(ax)`` on a fixed frame, return the RGB image (H, W, 3) in [0, 1]."""
    fig = Figure(figsize=(size[0] / 100, size[1] / 100), dpi=100)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_axis_off()
    draw(ax)
    ax.set_xlim(*xlim)
    ax.set_ylim(*ylim)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3] / 255.0


def skin_mask(img):
    """Pixels of the skin-coloured body: clearly warmer than the grey/white background."""
    return (img[..., 0] - img[..., 2]) > 0.08


# --------------------------------------------------------------------------------- projection

def test_project_axes_follow_documented_cameras():
    pts = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])     # +X (left side), up, front
    xy, depth = R.project(pts, "front")
    assert xy[0, 0] > 0 and xy[1, 1] > 0                       # person's left on image right
    assert depth[2] < depth[0]                                  # the front is nearest
    xy, depth = R.project(pts, "back")
    assert xy[0, 0] < 0 and depth[2] > depth[0]
    xy, depth = R.project(pts, "side")
    assert xy[2, 0] < 0 and xy[1, 1] > 0                        # face points to image left
    assert depth[0] < depth[2]                                  # camera on the +X side
    xy, depth = R.project(pts, "top")
    assert xy[0, 0] > 0 and xy[2, 1] < 0 and depth[1] < depth[0]


def test_project_is_orthographic_and_keeps_units():
    v = np.random.default_rng(0).normal(size=(50, 3))
    xy, depth = R.project(v, "front")
    np.testing.assert_allclose(xy, v[:, :2])
    np.testing.assert_allclose(depth, -v[:, 2])


# ------------------------------------------------------------------------------------ shading

@pytest.mark.parametrize("view", R.VIEWS)
def test_backface_culling_drops_about_half_a_sphere(view):
    v, f = sphere()
    s = R.shade(v, f, view)
    culled = np.isnan(s).mean()
    assert 0.45 < culled < 0.55
    lit = s[~np.isnan(s)]
    assert lit.min() >= 0.25 - 1e-12 and lit.max() <= 1.0


def test_light_comes_from_the_camera_upper_left():
    v, f = sphere()
    s = R.shade(v, f, "front", smooth=False)
    xy, _ = R.project(v[f].mean(axis=1), "front")
    vis = ~np.isnan(s)
    upper_left = vis & (xy[:, 0] < -0.3) & (xy[:, 1] > 0.3)
    lower_right = vis & (xy[:, 0] > 0.3) & (xy[:, 1] < -0.3)
    assert s[upper_left].mean() > s[lower_right].mean() + 0.3
    # The brightest face's normal points at the light, within the icosphere's facet size.
    n = trimesh.Trimesh(v, f, process=False).face_normals
    # In the front view camera axes (right, up, toward the camera) are world X, Y, Z.
    light = np.array(R.DEFAULT_LIGHT) / np.linalg.norm(R.DEFAULT_LIGHT)
    assert n[np.nanargmax(s)] @ light > 0.98


def test_flipped_faces_are_culled_from_the_other_side():
    v, f = sphere()
    seen = ~np.isnan(R.shade(v, f, "front"))
    seen_flipped = ~np.isnan(R.shade(v, f[:, ::-1], "front"))
    assert not (seen & seen_flipped).any()
    # Only faces seen exactly edge-on (the icosphere has a ring of them) are in neither.
    assert (seen | seen_flipped).mean() > 0.95


# ------------------------------------------------------------------------------------ drawing

def test_draw_mesh_is_shaded_not_flat():
    v, f = sphere()
    img = render_ax(lambda ax: R.draw_mesh(ax, v, f, "front"))
    body = skin_mask(img)
    assert 0.4 < body.mean() < 0.7                       # a disc of radius 1 in a 2.4 x 2.4 frame
    lum = img[body].mean(axis=1)
    assert lum.std() > 0.05
    assert np.percentile(lum, 95) - np.percentile(lum, 5) > 0.2


def test_front_and_side_silhouettes_of_an_ellipsoid():
    v, f = ellipsoid((0.4, 0.9, 0.15))
    widths = {}
    for view in ("front", "side"):
        img = render_ax(lambda ax: R.draw_mesh(ax, v, f, view), xlim=(-1, 1), ylim=(-1, 1),
                        size=(300, 300))
        cols = np.flatnonzero(skin_mask(img).any(axis=0))
        rows = np.flatnonzero(skin_mask(img).any(axis=1))
        widths[view] = np.ptp(cols) + 1
        assert abs((np.ptp(rows) + 1) - 0.9 * 300) < 8      # same height in both views
    assert abs(widths["front"] - 0.4 * 300) < 6           # 2 x 0.4 m of a 2 m frame
    assert abs(widths["side"] - 0.15 * 300) < 6
    assert widths["front"] / widths["side"] == pytest.approx(0.4 / 0.15, rel=0.15)


def test_painter_algorithm_ignores_input_face_order():
    # A small sphere in front of (and overlapping) a large one, in one mesh.
    v1, f1 = sphere(1.0, (0.0, 0.0, -1.5))
    v2, f2 = sphere(0.4, (0.5, 0.3, 0.0))
    va, fa = np.vstack([v1, v2]), np.vstack([f1, f2 + len(v1)])       # far first
    vb, fb = np.vstack([v2, v1]), np.vstack([f2, f1 + len(v2)])       # near first
    img_a = render_ax(lambda ax: R.draw_mesh(ax, va, fa, "front"))
    img_b = render_ax(lambda ax: R.draw_mesh(ax, vb, fb, "front"))
    assert np.abs(img_a - img_b).max() < 1e-6
    # And the near sphere is what shows: its bright centre equals the small sphere alone.
    img_small = render_ax(lambda ax: R.draw_mesh(ax, v2, f2, "front"))
    centre = (round((1.2 - 0.3) / 2.4 * 240), round((0.5 + 1.2) / 2.4 * 240))   # (row, col)
    np.testing.assert_allclose(img_b[centre], img_small[centre], atol=1e-6)


def test_draw_polyline_projects_with_the_same_view():
    pts = np.array([[0.0, 0.5, 0.2], [0.3, 0.5, 0.0], [0.0, 0.5, -0.2]])
    fig = Figure()
    ax = fig.add_axes((0, 0, 1, 1))
    line = R.draw_polyline(ax, pts, "side", offset=(1.0, 0.0), closed=True)
    x, y = line.get_data()
    np.testing.assert_allclose(x, [0.8, 1.0, 1.2, 0.8])
    np.testing.assert_allclose(y, 0.5)


def test_rendering_a_body_sized_mesh_is_fast():
    m = trimesh.creation.capsule(height=1.4, radius=0.2, count=[130, 104])   # ~26.8k faces
    assert len(m.faces) > 25_000
    t0 = time.perf_counter()
    render_ax(lambda ax: R.draw_mesh(ax, m.vertices, m.faces, "front"), size=(300, 600))
    # Typically ~0.15 s; the bound only catches a Python loop over faces.
    assert time.perf_counter() - t0 < 1.5


# ------------------------------------------------------------------------------ contact sheet

def test_contact_sheet_writes_a_shaded_png(tmp_path):
    bodies = [upright_capsule(h) for h in (1.5, 1.7, 1.9)]
    path = R.contact_sheet([b[0] for b in bodies], bodies[0][1], tmp_path / "sheet.png",
                           labels=["a", "b", "c"], views=("front", "side"), title="capsules",
                           dpi=60)
    assert path.exists() and list(tmp_path.iterdir()) == [path]
    img = imread(path)[..., :3]
    assert img.std() > 0.05
    lum = img[skin_mask(img)].mean(axis=1)
    assert lum.size > 1000
    assert np.percentile(lum, 95) - np.percentile(lum, 5) > 0.15


def test_contact_sheet_pixel_size(tmp_path):
    v, f = upright_capsule(1.8)
    def size(n, dpi, **kw):
        p = R.contact_sheet([v] * n, f, tmp_path / f"s{n}_{dpi}.png", dpi=dpi, **kw)
        return imread(p).shape[:2]
    h1, w1 = size(2, 40)
    h2, w2 = size(2, 80)
    assert abs(h2 - 2 * h1) <= 1 and abs(w2 - 2 * w1) <= 1
    # A single line-up: same height; each body adds the same width.
    h4, w4 = size(4, 40)
    w2 = w1
    assert h4 == h1 and abs((w4 - w2) - 2 * (w2 - size(1, 40)[1])) <= 2
    # panel_height sets the body's size in inches: the picture is about that tall.
    assert 2.4 * 40 < h1 < 3.5 * 40
    # 60 bodies: a grid capped at max_inches on its longer side.
    h60, w60 = size(60, 20, max_inches=20)
    assert max(h60, w60) <= 20 * 20 + 1 and min(h60, w60) > 100


def test_contact_sheet_wraps_a_long_title_inside_the_picture(tmp_path):
    # An animate filmstrip's title ran off both edges of a two-body sheet.
    v, f = upright_capsule(1.7)
    title = "131_01 on child.ply (skeleton embedded (mesh up z, mm; fit residual 1.9 mm), " * 3
    path = R.contact_sheet([v, v], f, tmp_path / "long.png", views=("front", "side"), title=title, dpi=60)
    img = imread(path)[..., :3]
    ink = img.mean(axis=2) < 0.5                        # dark text (the body is skin, the ruler grey)
    rows = np.flatnonzero(ink.any(axis=1))
    assert rows.size and not ink[:, :2].any() and not ink[:, -2:].any()
    # Several lines of text above the bodies, none cut at the top.
    assert not ink[:2].any()
    text_rows = rows[rows < np.flatnonzero(skin_mask(img).any(axis=1)).min()]
    assert np.ptp(text_rows) > 2 * 9 * 60 / 72


def test_a_weight_map_is_drawn_from_the_side_the_weight_is_on():
    # A spine bone's weight lies on the back: drawn from the front its map was blank.
    v, f = ellipsoid()
    facing = mesh_normals(v, f)[:, 2]
    back, front = (v[:, 2] < -0.05).astype(float), (v[:, 2] > 0.05).astype(float)
    assert weight_view(back, facing) == "back" and weight_view(front, facing) == "front"


def test_contact_sheet_uses_one_vertical_scale(tmp_path):
    (v1, f), (v2, _) = upright_capsule(1.0), upright_capsule(2.0)
    v2 = v2 + [0.0, 0.3, 0.0]              # not on y=0: the sheet must still stand it on the floor
    path = R.contact_sheet([v1, v2], f, tmp_path / "lineup.png", dpi=60, ruler=False)
    mask = skin_mask(imread(path)[..., :3])
    half = mask.shape[1] // 2
    heights = [np.ptp(np.flatnonzero(m.any(axis=1))) + 1 for m in (mask[:, :half], mask[:, half:])]
    assert heights[1] / heights[0] == pytest.approx(2.0, rel=0.05)
    # Common ground: both stand on the same floor row.
    bottoms = [np.flatnonzero(m.any(axis=1)).max() for m in (mask[:, :half], mask[:, half:])]
    assert abs(bottoms[0] - bottoms[1]) <= 1


def test_contact_sheet_accepts_a_batch_array_and_overlays(tmp_path):
    v, f = upright_capsule(1.7)
    loop = np.c_[0.15 * np.cos(np.linspace(0, 2 * np.pi, 40)), np.full(40, 1.0),
                 0.15 * np.sin(np.linspace(0, 2 * np.pi, 40))]
    path = R.contact_sheet(np.stack([v, v]), f, tmp_path / "b.png", dpi=50,
                           polylines=[[loop], []], ruler=False)
    img = imread(path)[..., :3]
    red = (img[..., 0] > 0.6) & (img[..., 1] < 0.35) & (img[..., 2] < 0.35)
    assert red.sum() > 10
    assert red[:, : img.shape[1] // 2].sum() > 10 and red[:, img.shape[1] // 2:].sum() == 0


def test_failed_write_leaves_no_file(tmp_path, monkeypatch):
    def boom(self, *args, **kwargs):
        Path(args[0]).write_bytes(b"half a png")          # as if interrupted mid-write
        raise RuntimeError("disk full")
    monkeypatch.setattr(Figure, "savefig", boom)
    v, f = sphere()
    with pytest.raises(RuntimeError, match="disk full"):
        R.contact_sheet([v], f, tmp_path / "sheet.png")
    with pytest.raises(RuntimeError, match="disk full"):
        R.histogram_figure([{"title": "x", "values": [1.0, 2.0]}], tmp_path / "hist.png")
    assert list(tmp_path.iterdir()) == []


def test_new_figure_and_save_png_are_public_building_blocks(tmp_path):
    """``report.landmarks`` builds its figure from these two: the size in pixels is width x dpi,
    and the PNG appears under its name only (no temporary file left beside it)."""
    fig = R.new_figure(2.0, 1.5, 50)
    fig.add_axes((0, 0, 1, 1)).plot([0, 1], [0, 1])
    out = R.save_png(fig, tmp_path / "fig.png", 50)
    assert out == tmp_path / "fig.png" and [p.name for p in tmp_path.iterdir()] == ["fig.png"]
    assert imread(out).shape[:2] == (75, 100)


# --------------------------------------------------------------------------------- histograms

def test_histogram_figure(tmp_path):
    rng = np.random.default_rng(1)
    men, women = rng.normal(1.76, 0.07, 300), rng.normal(1.63, 0.065, 300)
    panels = [
        {"title": "stature, men", "values": men, "target_mean": 1.76, "target_sd": 0.07,
         "xlabel": "m"},
        {"title": "stature, women", "values": women, "target_mean": 1.63, "target_sd": 0.065},
        {"title": "BMI", "groups": {"men": rng.normal(27, 4, 300), "women": rng.normal(26, 5, 300)},
         "target_mean": 26.5, "target_sd": 4.5, "xlabel": "kg/m²"},
        {"title": "no target", "values": men},
    ]
    path = R.histogram_figure(panels, tmp_path / "h.png", title="population", dpi=50)
    img = imread(path)[..., :3]
    assert img.shape[:2] == (2 * 3 * 50, 2 * 4 * 50)
    assert img.std() > 0.05
    red = (img[..., 0] > 0.6) & (img[..., 1] < 0.35) & (img[..., 2] < 0.35)    # target curves
    h, w = img.shape[:2]
    assert red[: h // 2].sum() > 20 and red[h // 2:, w // 2:].sum() == 0   # none without target


# ------------------------------------------------------------------------------------- errors

def test_shape_errors_name_found_and_expected(tmp_path):
    v, f = sphere()
    with pytest.raises(MeshError, match=r"shape \(10, 2\), expected \(V, 3\)"):
        R.project(np.zeros((10, 2)))
    with pytest.raises(MeshError, match=r"shape \(4, 4\), expected \(F, 3\)"):
        R.shade(v, np.zeros((4, 4), int))
    with pytest.raises(MeshError, match=r"expected 0\.\.641"):
        R.shade(v, f + 1)
    with pytest.raises(MeshError, match="NaN"):
        R.project(np.full((3, 3), np.nan))
    with pytest.raises(MeshError, match=r"meshes: shape \(642, 3\)"):
        R.contact_sheet(v, f, tmp_path / "x.png")
    with pytest.raises(MeshError, match=r"faces: got 1 face arrays for 2 meshes"):
        R.contact_sheet([v, v], [f], tmp_path / "x.png")
    with pytest.raises(MeshError, match=r"points3d: shape \(3, 2\)"):
        R.draw_polyline(Figure().add_subplot(), np.zeros((3, 2)), "front")
    with pytest.raises(ParameterError, match="view: got 'left'"):
        R.project(v, "left")
    with pytest.raises(ParameterError, match="labels: got 1 labels for 2 meshes"):
        R.contact_sheet([v, v], f, tmp_path / "x.png", labels=["a"])
    with pytest.raises(ParameterError, match=r"panels\[0\]\['values'\]: shape \(2, 2\)"):
        R.histogram_figure([{"title": "t", "values": np.zeros((2, 2))}], tmp_path / "h.png")
    with pytest.raises(ParameterError, match=r"unknown keys \['mean'\]"):
        R.histogram_figure([{"values": [1.0], "mean": 1.0}], tmp_path / "h.png")
    assert list(tmp_path.iterdir()) == []
