"""Detail transfer (Hasler §3, end; issue 15): does a scan's relief survive a morph?

A test body (an edge-of-population phenotype, rest pose) gets a relief of known amplitude: the
template subdivided twice at mid-edges (1.6 mm edges) and each vertex moved along the normal
by h(x) = A sin(2πx/λ) sin(2πy/λ) sin(2πz/λ + 1) of its point on the template's rest body (so the
relief is attached to the skin and moves with it; A = 4 mm, λ = 4 cm: bumps ~2 cm apart,
1.0 mm mean |h|). That surface is sampled as a scan (millimetres, Z up, turned, noise σ).

Per scan, in one process:
- ``register_scan(detail_levels=1)``: the fit and the relief over it (``detail_offsets``);
- a morph: the same displacement field (another phenotype's body minus this one's, ~cm) added
  to the fit and to the true body; the truth after it is the true relief on the morphed true
  body (``apply_detail`` with the true offsets);
- scores: mean distance of the morphed fit's subdivided vertices from the true detailed morphed
  surface, without the detail (the smooth fit) and with it (``apply_detail``); the same with the
  true body as the base (the detail step alone, no registration error); the offsets' error
  against the true relief per subdivided vertex.

    python benchmarks/bench_detail.py [--seeds 11 12] [--points 200000] [--sigma 0.5]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bodyspace.data.template import load_template
from bodyspace.measure import load_measurement_set
from bodyspace.measure.parts import PART_INDEX
from bodyspace.mesh.geometry import vertex_normals
from bodyspace.mesh.topology import edges
from bodyspace.register.detail import apply_detail, detail_offsets, midpoint_subdivide
from bodyspace.register.pipeline import register_scan
from bodyspace.synth.foreign import closest_points, foreign_phenotype, from_frame, to_frame
from bodyspace.synth.phenotype import PARAMETERS, PhenotypeModel
from bodyspace.synth.scans import SCAN_FRAME, sample_surface

AMPLITUDE = 0.004
WAVELENGTH = 0.04


def relief(x: np.ndarray) -> np.ndarray:
    k = 2 * np.pi / WAVELENGTH
    return AMPLITUDE * np.sin(k * x[:, 0]) * np.sin(k * x[:, 1]) * np.sin(k * x[:, 2] + 1.0)


def detailed(body, faces, anchor, levels):
    """``body`` subdivided, each vertex moved along its normal by the relief of its point on ``anchor``."""
    v, f = midpoint_subdivide(body, faces, levels)
    a, _ = midpoint_subdivide(anchor, faces, levels)
    return v + relief(a)[:, None] * vertex_normals(v, f), f


def surface_distance(points, vertices, faces, where=None) -> float:
    d = closest_points(points, vertices, faces)[1]
    return 1000 * float(d.mean() if where is None else d[where].mean())


def body_mask(template) -> np.ndarray:
    """(S,) bool over the once-subdivided vertices: on the torso, neck and limbs (not the head,
    hands or feet, whose folds - ears, lips, fingers, toes - are finer than the scan's sampling)."""
    parts = load_measurement_set().vertex_parts
    e = edges(template.faces)
    sub = np.concatenate([parts, np.minimum(parts[e[:, 0]], parts[e[:, 1]])])
    fine = [PART_INDEX[p] for p in ("head", "hand_l", "hand_r", "foot_l", "foot_r")]
    return ~np.isin(sub, fine)


def run(seed: int, n_points: int, sigma: float, template, pm) -> dict:
    rng = np.random.default_rng(seed)
    faces = template.faces
    phen = foreign_phenotype(rng)
    body = pm.vertices(phen[None])[0]
    body = body - [0.0, body[:, 1].min(), 0.0]
    other = phen.copy()
    which = [PARAMETERS.index("weight"), PARAMETERS.index("muscle")]
    other[which] = np.clip(other[which] + [0.3, -0.3], 0, 1)         # a heavier, less muscular build
    delta = pm.vertices(other[None])[0] - pm.vertices(phen[None])[0]
    true2, f2 = detailed(body, faces, template.vertices, 2)
    pts = sample_surface(true2, f2, n_points, rng)[0] + rng.normal(0, sigma, (n_points, 3))
    frame = dict(SCAN_FRAME, yaw_degrees=float(rng.uniform(0, 360)))
    scan = to_frame(pts, **frame)

    t = time.perf_counter()
    reg = register_scan(scan, units="mm", up="z", detail_levels=1, rng=seed)
    seconds = time.perf_counter() - t
    fit = from_frame(reg.vertices, **frame)                      # the true body's frame, metres
    # The detail was taken in bodyspace's frame; offsets are lengths along normals, the same in
    # any rigid frame: re-add them on the fit brought to the truth's frame.
    morphed_true, mf = detailed(body + delta, faces, template.vertices, 2)
    smooth = midpoint_subdivide(fit + delta, faces, 1)[0]
    with_detail = apply_detail(fit + delta, faces, reg.detail)[0]
    # The detail step alone: offsets taken with the true body as the fit.
    ideal = detail_offsets(body, faces, pts, levels=1)
    ideal_smooth = midpoint_subdivide(body + delta, faces, 1)[0]
    ideal_detail = apply_detail(body + delta, faces, ideal)[0]
    h_true = relief(midpoint_subdivide(template.vertices, faces, 1)[0])
    v = reg.detail.valid
    trunk = body_mask(template)
    return {
        "body_fit_smooth_mm": surface_distance(smooth, morphed_true, mf, trunk),
        "body_fit_detail_mm": surface_distance(with_detail, morphed_true, mf, trunk),
        "body_ideal_smooth_mm": surface_distance(ideal_smooth, morphed_true, mf, trunk),
        "body_ideal_detail_mm": surface_distance(ideal_detail, morphed_true, mf, trunk),
        "body_offset_err_ideal_mm": 1000 * float(np.abs(ideal.offsets - h_true)[ideal.valid & trunk].mean()),
        "seed": seed, "seconds": seconds, "valid": float(v.mean()), "quality": reg.quality.quality,
        "fit_smooth_mm": surface_distance(smooth, morphed_true, mf),
        "fit_detail_mm": surface_distance(with_detail, morphed_true, mf),
        "ideal_smooth_mm": surface_distance(ideal_smooth, morphed_true, mf),
        "ideal_detail_mm": surface_distance(ideal_detail, morphed_true, mf),
        "offset_err_fit_mm": 1000 * float(np.abs(reg.detail.offsets - h_true)[v].mean()),
        "offset_err_ideal_mm": 1000 * float(np.abs(ideal.offsets - h_true)[ideal.valid].mean()),
        "relief_mean_mm": 1000 * float(np.abs(h_true).mean()),
        "detail_seconds": reg.seconds.get("detail", float("nan")),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[11, 12])
    ap.add_argument("--points", type=int, default=200_000)
    ap.add_argument("--sigma", type=float, default=0.5, help="scan noise per coordinate, mm")
    args = ap.parse_args()
    template = load_template()
    pm = PhenotypeModel(template)
    rows = []
    for seed in args.seeds:
        r = run(seed, args.points, args.sigma / 1000, template, pm)
        rows.append(r)
        print(f"seed {seed}: {args.points} points, sigma {args.sigma} mm; quality {r['quality']:.2f}, "
              f"{100 * r['valid']:.1f} % of subdivided vertices on the scan; registration {r['seconds']:.1f} s "
              f"(detail {r['detail_seconds']:.1f} s)")
        print(f"  distance of the morphed body from the true detailed morph: fit smooth {r['fit_smooth_mm']:.2f} mm, "
              f"fit + detail {r['fit_detail_mm']:.2f} mm; true base smooth {r['ideal_smooth_mm']:.2f} mm, "
              f"true base + detail {r['ideal_detail_mm']:.2f} mm")
        print(f"  offsets vs the true relief (mean |h| {r['relief_mean_mm']:.2f} mm): on the fit "
              f"{r['offset_err_fit_mm']:.2f} mm, on the true base {r['offset_err_ideal_mm']:.2f} mm")
        print(f"  torso, neck and limbs only: fit smooth {r['body_fit_smooth_mm']:.2f} -> fit + detail "
              f"{r['body_fit_detail_mm']:.2f} mm; true base smooth {r['body_ideal_smooth_mm']:.2f} -> + detail "
              f"{r['body_ideal_detail_mm']:.2f} mm; offsets on the true base {r['body_offset_err_ideal_mm']:.2f} mm")
        print(f"RATIO detail/smooth surface error (fit): {r['fit_detail_mm'] / r['fit_smooth_mm']:.2f}; "
              f"(true base): {r['ideal_detail_mm'] / r['ideal_smooth_mm']:.2f}")
    if len(rows) > 1:
        mean = {k: np.mean([r[k] for r in rows]) for k in rows[0] if k != "seed"}
        print(f"mean: fit smooth {mean['fit_smooth_mm']:.2f} mm -> with detail {mean['fit_detail_mm']:.2f} mm; "
              f"true base smooth {mean['ideal_smooth_mm']:.2f} -> {mean['ideal_detail_mm']:.2f} mm")


if __name__ == "__main__":
    main()
