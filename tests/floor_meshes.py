"""Meshes a scanner makes: a body with its floor (a separate disc, a sheet welded to the soles), a
turntable or a pole beside it. Shared by the floor tests of measure and rig (test_measure_floor,
test_rig_floor). Bodies in metres, +Y up, standing on their lowest point."""

from __future__ import annotations

import numpy as np


def disc(centre, radius, y, rings=6, seg=40):
    """A flat disc (P, 3), (F, 3) at height y, its faces wound to face +Y."""
    pts = [np.array([centre[0], y, centre[2]])]
    a = np.linspace(0, 2 * np.pi, seg, endpoint=False)
    for i in range(1, rings + 1):
        r = radius * i / rings
        pts += list(np.c_[centre[0] + r * np.cos(a), np.full(seg, y), centre[2] + r * np.sin(a)])
    faces = [[0, 1 + (j + 1) % seg, 1 + j] for j in range(seg)]
    for i in range(1, rings):
        b0, b1 = 1 + (i - 1) * seg, 1 + i * seg
        for j in range(seg):
            k = (j + 1) % seg
            faces += [[b0 + j, b0 + k, b1 + k], [b0 + j, b1 + k, b1 + j]]
    p, f = np.array(pts), np.array(faces)
    if np.cross(p[f[0, 1]] - p[f[0, 0]], p[f[0, 2]] - p[f[0, 0]])[1] < 0:
        f = f[:, ::-1]
    return p, f


def welded_sheet(v, size=1.6, n=33):
    """A square sheet (n x n grid) at the soles' height whose points over the soles are the soles'
    own vertices (one connected mesh): (vertices (V + G, 3), faces (F_sheet, 3) into them)."""
    y0 = v[:, 1].min()
    xs = np.linspace(-size / 2, size / 2, n)
    x, z = np.meshgrid(xs, xs + v[:, 2].mean())
    grid = np.c_[x.ravel(), np.full(n * n, y0), z.ravel()]
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j + 1, (i + 1) * n + j
            faces += [[a, c, b], [a, d, c]]
    faces = np.array(faces)
    sole = np.flatnonzero(v[:, 1] < y0 + 0.004)
    ids = np.arange(n * n) + len(v)
    d = np.linalg.norm(grid[:, None, [0, 2]] - v[sole][None, :, [0, 2]], axis=2)
    near = d.min(axis=1) < 0.03
    ids[near] = sole[d.argmin(axis=1)[near]]
    return np.r_[v, grid], ids[faces]


def turntable(centre, radius, y_top, depth, rings=3, seg=40):
    """A closed flat cylinder (P, 3), (F, 3): its top at y_top, its side ``depth`` deep, wound outwards."""
    top_v, top_f = disc(centre, radius, y_top, rings, seg)
    bot_v, bot_f = disc(centre, radius, y_top - depth, rings, seg)
    n = len(top_v)
    rim = np.arange(n - seg, n)
    side = []
    for j in range(seg):
        k = (j + 1) % seg
        side += [[rim[j], rim[j] + n, rim[k] + n], [rim[j], rim[k] + n, rim[k]]]
    side = np.array(side)
    f = np.r_[top_f, bot_f[:, ::-1] + n, side]
    p = np.r_[top_v, bot_v]
    # the side faces outwards (away from the axis)
    c = p[side].mean(axis=1)
    nrm = np.cross(p[side[:, 1]] - p[side[:, 0]], p[side[:, 2]] - p[side[:, 0]])
    if (np.einsum("ij,ij->i", nrm[:, [0, 2]], c[:, [0, 2]] - np.asarray(centre)[[0, 2]]) < 0).mean() > 0.5:
        f[len(top_f) + len(bot_f):] = side[:, ::-1]
    return p, f


def pole(x, z, y0, height=2.0, radius=0.02):
    """A thin 2 m pole (P, 3), (F, 3) standing at (x, z) from y0 (a stand or a stool's leg alike)."""
    pv, pf = disc((x, 0.0, z), radius, y0, rings=1, seg=8)
    m = len(pv)
    return np.r_[pv, pv + (0, height, 0)], np.r_[pf, pf + m, [[1, 2, 2 + m]]]


def with_extras(v, f, *extras):
    """The body (V, 3), (F, 3) and extra pieces [(P, 3), (F', 3)] as one mesh, the body's vertices first."""
    vs, fs, n = [v], [f], len(v)
    for ev, ef in extras:
        vs.append(ev)
        fs.append(ef + n)
        n += len(ev)
    return np.concatenate(vs), np.concatenate(fs)


def scanner_meshes(v, f):
    """name → (vertices, faces) of the body (V, 3), (F, 3) metres +Y up with (a) a separate floor
    disc 1.6 m wide, (b) a sheet welded to its soles, (c) a turntable under it, (d) a pole beside it;
    the body's vertices first and its faces first in every one."""
    y0 = v[:, 1].min()
    zc = v[:, 2].mean()
    sheet_v, sheet_f = welded_sheet(v)
    return {
        "disc": with_extras(v, f, disc((0.0, 0.0, zc), 0.8, y0)),
        "welded": (sheet_v, np.r_[f, sheet_f]),
        "turntable": with_extras(v, f, turntable((0.0, 0.0, zc), 0.5, y0, 0.1)),
        "pole": with_extras(v, f, pole(0.75, 0.0, y0)),
    }
