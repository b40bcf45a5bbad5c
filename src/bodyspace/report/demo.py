"""The README's main job: assets → a synthetic population → pictures and a JSON summary.

``run_demo`` is what ``bodyspace demo`` calls; it only composes the public API, so every step it
shows is one a user can run on its own (``bodyspace assets``, ``bodyspace population`` ...).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import numpy as np

from bodyspace.atomic import write_json
from bodyspace.data import assets
from bodyspace.data.population import build_population, load_survey
from bodyspace.data.template import load_template
from bodyspace.encoding import VertexEncoder
from bodyspace.model import BodyModel
from bodyspace.report.render import contact_sheet, histogram_figure
from bodyspace.report.shape_report import (generalization_study, interpolation_study, write_generalization_report,
                                           write_interpolation_report)

# Shape-space part of the demo: components of the pose+shape model, bodies sampled, subjects in
# the interpolation study and held-out subjects in the generalization study (cost: ~0.3 s per
# RRE decode on 2 cores; see report/shape_report.py).
POSE_SHAPE_COMPONENTS = 30
SAMPLES = 8
INTERPOLATION_SUBJECTS = 2
GENERALIZATION_FOLDS = 5
GENERALIZATION_COMPONENTS = (1, 4, 16)


def population_summary(db, survey: dict) -> dict:
    """Per-sex stature and BMI mean/SD of a population against the survey's targets."""
    sex = db.subjects["sex"]
    out = {}
    for s in ("female", "male"):
        k = sex == s
        st, bmi, mass = db.subjects["stature_cm"][k], db.subjects["bmi_kg_m2"][k], db.subjects["mass_kg"][k]
        out[s] = {
            "subjects": int(k.sum()),
            "stature_cm": {"mean": float(st.mean()), "sd": float(st.std()),
                           "target_mean": survey[s]["stature_mean"], "target_sd": survey[s]["stature_sd"]},
            "bmi_kg_m2": {"mean": float(bmi.mean()), "sd": float(bmi.std()),
                          "target_mean": float(survey[s]["bmi_mean"]), "target_sd": float(survey[s]["bmi_sd"])},
            "mass_kg": {"mean": float(mass.mean()), "sd": float(mass.std()),
                        "survey_mean": survey[s]["mass_mean"], "survey_sd": survey[s]["mass_sd"]},
            "body_fat_percent_mean": float(db.subjects["body_fat_percent"][k].mean()),
        }
    return out


def run_demo(out: str | Path, subjects: int = 24, poses: int = 5, seed: int = 0, assets_root=None,
             progress: Callable[[str, float], None] | None = None) -> dict:
    """Fetch the assets, build a population, write PNGs and ``summary.json`` into ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    report = progress or (lambda msg, frac: None)
    timings = {}

    t = time.perf_counter()
    report("fetching and verifying the CC0 assets", 0.0)
    root = assets.fetch(assets_root)
    template = load_template(root)
    timings["assets_and_template_s"] = time.perf_counter() - t

    t = time.perf_counter()
    db = build_population(template, out / "population", subjects, poses, rng=seed, overwrite=True,
                          progress=lambda m, f: report(m, 0.05 + 0.6 * f))
    timings["population_s"] = time.perf_counter() - t

    t = time.perf_counter()
    report("rendering pictures", 0.7)
    rest = db.rest_pose()
    sex, st, mass = rest.subjects["sex"], rest.subjects["stature_cm"], rest.subjects["mass_kg"]
    order = np.argsort(st)
    labels = [f"{sex[i][0].upper()} {st[i]:.0f} cm\n{mass[i]:.0f} kg" for i in order]
    contact_sheet(np.asarray(rest.vertices)[order], db.faces, out / "lineup.png", labels=labels,
                  title=f"{len(order)} synthetic adults, rest pose, sorted by stature")
    first = db.scans["subject"][0]
    mine = np.flatnonzero(db.scans["subject"] == first)
    contact_sheet(np.asarray(db.vertices[mine]), db.faces, out / "poses.png",
                  labels=list(db.scans["pose"][mine]), views=("front", "side"),
                  title=f"subject {first} in {len(mine)} scans (front and side)")
    # A mixed sheet: one random posed scan per subject, for a feel of the database.
    rng = np.random.default_rng(seed)
    per = len(db) // rest.n_scans
    pick = np.arange(rest.n_scans) * per + rng.integers(0, per, rest.n_scans)
    contact_sheet(np.asarray(db.vertices[np.sort(pick)]), db.faces, out / "scans.png",
                  labels=list(db.scans["pose"][np.sort(pick)]), title="one scan per subject")
    survey = load_survey()
    summary_pop = population_summary(db, survey)
    panels = []
    for quantity, key, unit in (("stature", "stature_cm", "cm"), ("BMI", "bmi_kg_m2", "kg/m²")):
        for s in ("female", "male"):
            k = db.subjects["sex"] == s
            tgt = summary_pop[s][key]
            panels.append({"title": f"{quantity}, {s}", "values": db.subjects[key][k], "xlabel": unit,
                           "target_mean": tgt["target_mean"], "target_sd": tgt["target_sd"]})
    histogram_figure(panels, out / "histograms.png",
                     title=f"Population vs. survey targets ({survey['id']})")
    timings["render_s"] = time.perf_counter() - t

    shape_summary = shape_space_demo(db, template, out, seed, timings,
                                     lambda m, f: report(m, 0.75 + 0.24 * f))

    summary = {
        "output": str(out.resolve()),
        "assets": str(root),
        "template": template.template_id,
        "database": {"path": "population", "scans": db.n_scans, "subjects": db.n_subjects,
                     "vertices": db.n_vertices, "poses": sorted(set(db.scans["pose"].tolist()))},
        "survey": survey["citation"],
        "population": summary_pop,
        "pictures": ["lineup.png", "poses.png", "scans.png", "histograms.png"] + shape_summary.pop("pictures"),
        **shape_summary,
        "timings_s": {k: round(v, 2) for k, v in timings.items()},
        "units": {"stature": "cm", "mass": "kg", "bmi": "kg/m^2", "interpolation": "fraction",
                  "generalization_error": "mm"},
    }
    write_json(out / "summary.json", summary)
    report("done", 1.0)
    return summary


def shape_space_demo(db, template, out: Path, seed: int, timings: dict, report) -> dict:
    """Fit the shape-only (rest scans) and pose+shape (all scans) RRE models, save the
    shape-only one as ``model.npz``, sample bodies, and run the interpolation and
    leave-one-subject-out studies; returns the summary entries (and ``pictures``)."""
    t = time.perf_counter()
    report("fitting the shape-only model (rest scans)", 0.0)
    shape = BodyModel.fit(db, "rre", "rest", template=template, on_flipped="ignore")
    shape.save(out / "model.npz")
    timings["model_shape_fit_s"] = time.perf_counter() - t

    t = time.perf_counter()
    report("fitting the pose+shape model (all scans)", 0.15)
    k = min(POSE_SHAPE_COMPONENTS, db.n_scans - 1)
    posed = BodyModel.fit(db, "rre", "all", n_components=k, template=template, on_flipped="ignore")
    timings["model_pose_shape_fit_s"] = time.perf_counter() - t

    t = time.perf_counter()
    report("sampling bodies", 0.35)
    kc = min(10, shape.n_components)
    bodies = shape.sample(SAMPLES, n_components=kc, sigma_range=2.0, rng=seed)
    contact_sheet(bodies, shape.faces, out / "samples.png", labels=[f"sample {i + 1}" for i in range(SAMPLES)],
                  title=f"random bodies of the shape-only model ({kc} components, within 2 SD)")
    timings["samples_s"] = time.perf_counter() - t

    t = time.perf_counter()
    vertex_all = VertexEncoder(template.vertices, template.faces).fit(np.asarray(db.vertices, dtype=float))
    interp = interpolation_study(db, {"rre": posed.encoder, "vertex": vertex_all}, n_subjects=INTERPOLATION_SUBJECTS,
                                 progress=lambda m, f: report(m, 0.45 + 0.25 * f))
    interp_files = write_interpolation_report(interp, db.faces, out)
    timings["interpolation_s"] = time.perf_counter() - t

    t = time.perf_counter()
    rest = db.rest_pose()
    vertex_rest = VertexEncoder(template.vertices, template.faces).fit(np.asarray(rest.vertices, dtype=float))
    general = generalization_study(db, {"rre": shape.encoder, "vertex": vertex_rest}, selection="rest",
                                   n_folds=GENERALIZATION_FOLDS,
                                   components=GENERALIZATION_COMPONENTS, progress=lambda m, f: report(m, 0.7 + 0.3 * f))
    general_files = write_generalization_report(general, out)
    timings["generalization_s"] = time.perf_counter() - t

    def model_entry(m):
        return {"encoding": m.encoding, "selection": m.selection, "scans": int(len(m.fitted_scans)),
                "components": m.n_components,
                "explained_variance": round(float(m.space.explained_variance_ratio_.sum()), 4)}

    return {
        "models": {"shape": {**model_entry(shape), "file": "model.npz"},
                   "pose_and_shape": {**model_entry(posed), "file": None}},
        "interpolation": {"subjects": interp["subjects"], "pairs": interp["pairs"], "summary": interp["summary"],
                          **interp_files},
        "generalization": {"selection": "rest", "folds": general["folds"], "components": general["components"],
                           "error_mm": general["error_mm"], **general_files},
        "pictures": ["samples.png", interp_files["png"], general_files["png"]],
    }
