"""The README's main job: assets → a synthetic population → pictures and a JSON summary.

``run_demo`` is what ``bodyspace demo`` calls; it only composes the public API, so every step it
shows is one a user can run on its own (``bodyspace assets``, ``bodyspace population`` ...).
"""

from __future__ import annotations

import csv
import time
import warnings
from pathlib import Path
from typing import Callable

import numpy as np

from bodyspace.atomic import atomic_dir, atomic_path, write_json
from bodyspace.data import assets
from bodyspace.data.template import load_template
from bodyspace.encoding import VertexEncoder
from bodyspace.model import BodyModel
from bodyspace.report.mapping_report import write_mapping_report
from bodyspace.report.render import contact_sheet, histogram_figure
from bodyspace.report.semantic_report import requests_in_display_units, write_request_report
from bodyspace.report.shape_report import (
    generalization_in_mm,
    write_generalization_report,
    write_interpolation_report,
)
from bodyspace.semantics.evaluation import RegressionTable, format_angle_table, format_rmse_table
from bodyspace.semantics.model import SemanticModel
from bodyspace.studies.generalization import generalization_study
from bodyspace.studies.interpolation import interpolation_study
from bodyspace.studies.mapping import evaluate_mapping
from bodyspace.studies.requests import request_study
from bodyspace.synth.population import build_population, load_survey
from bodyspace.units import kind_of
from bodyspace.validation import as_seed

# Shape-space part of the demo: components of the pose+shape model, bodies sampled, subjects in
# the interpolation study, and the generalization study: held-out subjects and component counts
# of the shape-only (rest scans) and the pose+shape (all scans) study, each with RRE's two
# projections and vertex PCA (cost: a code projection ~0.3 s per RRE decode on 2 cores, a
# vertex fit up to 10 decodes and 4 Jacobians of k tangent directions: the posed study stops at
# 32 components, as fits at all ~140 would be most of the demo's time; benchmarks/
# study_generalization.py measures the full table, see docs/encoding.md).
POSE_SHAPE_COMPONENTS = 30
SAMPLES = 8
INTERPOLATION_SUBJECTS = 1
GENERALIZATION_FOLDS = 4
GENERALIZATION_COMPONENTS = (1, 4, 8, 16)
POSED_GENERALIZATION_FOLDS = 2
POSED_GENERALIZATION_COMPONENTS = (1, 4, 8, 16, 32)
# Semantic part: requested bodies, a crowd, and the random-request study: the 200
# requests (~0.08 s each on 2 cores with the vertex model). Below SEMANTIC_MIN_SUBJECTS (e.g.
# the CLI test's 4) the study is skipped.
DEMO_REQUESTS = 200
SEMANTIC_MIN_SUBJECTS = 8
CROWD = 12
REQUESTED = (("180 cm, 80 kg, male", {"stature": 1.80, "mass": 80.0, "sex": 1.0}),
             ("165 cm, 60 kg, female", {"stature": 1.65, "mass": 60.0, "sex": 0.0}),
             ("190 cm, 95 kg, male", {"stature": 1.90, "mass": 95.0, "sex": 1.0}),
             ("155 cm, 50 kg, female", {"stature": 1.55, "mass": 50.0, "sex": 0.0}))
TALLER_CM = (0, 3, 6, 9)
# Mapping part: training bodies and held-out requests (the 10,000 / 1,000; the vertex
# model makes them in well under a second, the forest trains in ~3 s on 2 cores).
MAPPING_SIZES = (10_000, 1_000)
# Kind in the .bodyspace marker of a demo folder (bodyspace.atomic).
DEMO_KIND = "demo"


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


def run_demo(out: str | Path, subjects: int = 24, poses: int = 5, rng=0, assets_root=None,
             progress: Callable[[str, float], None] | None = None, overwrite: bool = False,
             flag: str = "overwrite=True") -> dict:
    """Fetch the assets, build a population, write PNGs and ``summary.json`` into the folder ``out``.

    The folder is built under a temporary name and renamed when complete (``atomic_dir``): a
    demo killed half-way leaves no half folder. An existing ``out`` is refused unless
    ``overwrite`` and it is a demo folder bodyspace wrote; ``flag`` names that switch in messages.
    ``rng`` (Generator, seed or None) gives one integer seed ``s``; every step derives its own
    stream from ``s`` (``s + i`` for the i-th generated body), so a seed repeats the demo.
    """
    out = Path(out)
    seed = as_seed(rng)
    with atomic_dir(out, overwrite=overwrite, kind=DEMO_KIND, flag=flag) as folder:
        return _run_demo_into(folder, out.resolve(), subjects, poses, seed, assets_root, progress)


def _run_demo_into(out: Path, final: Path, subjects: int, poses: int, seed: int, assets_root,
                   progress: Callable[[str, float], None] | None) -> dict:
    """run_demo's work, written into the temporary folder ``out`` that becomes ``final``."""
    report = progress or (lambda msg, frac: None)
    timings = {}

    t = time.perf_counter()
    report("fetching and verifying the CC0 assets", 0.0)
    root = assets.fetch(assets_root)
    template = load_template(root)
    timings["assets_and_template_s"] = time.perf_counter() - t

    t = time.perf_counter()
    db = build_population(template, out / "population", subjects, poses, rng=seed,
                          progress=lambda m, f: report(m, 0.05 + 0.6 * f))
    timings["population_s"] = time.perf_counter() - t

    t = time.perf_counter()
    report("rendering pictures", 0.7)
    rest = db.rest_pose()
    sex, st, mass = rest.subjects["sex"], rest.subjects["stature_cm"], rest.subjects["mass_kg"]
    order = np.argsort(st)
    labels = [f"{sex[i][0].upper()} {st[i]:.0f} cm\n{mass[i]:.0f} kg" for i in order]
    contact_sheet(rest.read(order), db.faces, out / "lineup.png", labels=labels,
                  title=f"{len(order)} synthetic adults, rest pose, sorted by stature")
    first = db.scans["subject"][0]
    mine = np.flatnonzero(db.scans["subject"] == first)
    contact_sheet(db.read(mine), db.faces, out / "poses.png",
                  labels=list(db.scans["pose"][mine]), views=("front", "side"),
                  title=f"subject {first} in {len(mine)} scans (front and side)")
    # A mixed sheet: one random posed scan per subject, for a feel of the database.
    gen = np.random.default_rng(seed)
    per = len(db) // rest.n_scans
    pick = np.arange(rest.n_scans) * per + gen.integers(0, per, rest.n_scans)
    contact_sheet(db.read(np.sort(pick)), db.faces, out / "scans.png",
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
                                     lambda m, f: report(m, 0.75 + 0.12 * f))
    # Semantics and the measurement mapping share one shape-only vertex-encoding model.
    t = time.perf_counter()
    report("fitting the shape-only vertex model", 0.87)
    vertex_model = BodyModel.fit(db, "vertex", "rest", template=template, on_flipped="ignore")
    timings["vertex_model_s"] = time.perf_counter() - t
    semantic_summary = semantic_demo(db, template, vertex_model, out, seed, timings,
                                     lambda m, f: report(m, 0.88 + 0.07 * f))
    mapping_summary = mapping_demo(vertex_model, out, seed, timings, lambda m, f: report(m, 0.95 + 0.05 * f))

    summary = {
        "output": str(final),
        "assets": str(root),
        "template": template.template_id,
        "database": {"path": "population", "scans": db.n_scans, "subjects": db.n_subjects,
                     "vertices": db.n_vertices, "poses": sorted(set(db.scans["pose"].tolist()))},
        "survey": survey["citation"],
        "population": summary_pop,
        "pictures": ["lineup.png", "poses.png", "scans.png", "histograms.png"] + shape_summary.pop("pictures")
                    + semantic_summary.pop("pictures") + mapping_summary.pop("pictures"),
        **shape_summary,
        **semantic_summary,
        **mapping_summary,
        "timings_s": {k: round(v, 2) for k, v in timings.items()},
        "units": {"stature": "cm", "mass": "kg", "bmi": "kg/m^2", "interpolation": "fraction",
                  "generalization_error": "mm"},
    }
    write_json(out / "summary.json", summary)
    report("done", 1.0)
    return summary


def shape_space_demo(db, template, out: Path, rng, timings: dict, report) -> dict:
    """Fit the shape-only (rest scans) and pose+shape (all scans) RRE models, save the
    shape-only one as ``model.npz``, sample bodies (``rng``: Generator, seed or None), and run
    the interpolation and leave-one-subject-out studies; returns the summary entries (and
    ``pictures``)."""
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
    bodies = shape.sample(SAMPLES, n_components=kc, sigma_range=2.0, rng=rng)
    contact_sheet(bodies, shape.faces, out / "samples.png", labels=[f"sample {i + 1}" for i in range(SAMPLES)],
                  title=f"random bodies of the shape-only model ({kc} components, within 2 SD)")
    timings["samples_s"] = time.perf_counter() - t

    t = time.perf_counter()
    vertex_all = VertexEncoder(template.vertices, template.faces).fit(db.read(np.arange(db.n_scans)))
    interp = interpolation_study(db, {"rre": posed.encoder, "vertex": vertex_all}, n_subjects=INTERPOLATION_SUBJECTS,
                                 progress=lambda m, f: report(m, 0.45 + 0.25 * f))
    interp_files = write_interpolation_report(interp, db.faces, out)
    timings["interpolation_s"] = time.perf_counter() - t

    t = time.perf_counter()
    rest = db.rest_pose()
    vertex_rest = VertexEncoder(template.vertices, template.faces).fit(np.asarray(rest.vertices, dtype=float))
    general = generalization_study(db, {"rre": shape.encoder, "vertex": vertex_rest}, selection="rest",
                                   n_folds=GENERALIZATION_FOLDS, components=GENERALIZATION_COMPONENTS,
                                   progress=lambda m, f: report(m, 0.7 + 0.1 * f))
    timings["generalization_s"] = time.perf_counter() - t
    t = time.perf_counter()
    general_posed = generalization_study(db, {"rre": posed.encoder, "vertex": vertex_all}, selection="all",
                                         n_folds=POSED_GENERALIZATION_FOLDS,
                                         components=POSED_GENERALIZATION_COMPONENTS,
                                         with_all_components=False,
                                         progress=lambda m, f: report(m, 0.8 + 0.2 * f))
    general_files = write_generalization_report([general, general_posed], out)
    timings["generalization_posed_s"] = time.perf_counter() - t

    def model_entry(m):
        return {"encoding": m.encoding, "selection": m.selection, "scans": int(len(m.fitted_scans)),
                "components": m.n_components,
                "explained_variance": round(float(m.space.explained_variance_ratio_.sum()), 4)}

    return {
        "models": {"shape": {**model_entry(shape), "file": "model.npz"},
                   "pose_and_shape": {**model_entry(posed), "file": None}},
        "interpolation": {"subjects": interp["subjects"], "pairs": interp["pairs"], "summary": interp["summary"],
                          **interp_files},
        "generalization": {**{name: {"selection": g["selection"], "folds": g["folds"], "components": g["components"],
                                     "error_mm": generalization_in_mm(g)["error_mm"],
                                     "seconds_per_mesh": g["fit_s"]}
                              for name, g in (("shape_only", general), ("pose_and_shape", general_posed))},
                           **general_files},
        "pictures": ["samples.png", interp_files["png"], general_files["png"]],
    }


def _cm_kg(values: dict) -> dict:
    """Measured labels in display units (cm, kg; sex and other model labels as they are)."""
    out = {}
    for k, v in values.items():
        kind = kind_of(k)
        out[f"{k}_cm" if kind == "length" else f"{k}_kg" if kind == "mass" else k] = \
            round(float(v) * (100.0 if kind == "length" else 1.0), 2)
    return out


def semantic_demo(db, template, bm: BodyModel, out: Path, rng, timings: dict, report) -> dict:
    """Fit the SemanticModel of shape-only model ``bm``, then: requested bodies
    (``requested.png``), taller at the same mass (``taller_same_weight.png``), a masked morph
    (``muscle_upper_body.png``), a crowd (``crowd.png``, ``crowd.csv``), Hasler Table 1 and Hasler Table 2
    (``semantic_tables.md``) and the random-request study (``requests.md``/``.json``).
    ``rng`` (Generator, seed or None) gives one seed ``s``; the i-th requested body uses ``s + i``."""
    seed = as_seed(rng)
    messages: list = []
    t = time.perf_counter()
    report("fitting the semantic model (vertex encoding, rest scans)", 0.0)
    sm = SemanticModel(bm, on_infeasible="clamp").fit(db, rng=seed, template=template)
    timings["semantic_fit_s"] = time.perf_counter() - t
    n_subj = len(sm.X_)
    faces = bm.faces

    def run(fn, *a, **kw):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", RuntimeWarning)
            r = fn(*a, **kw)
        messages.extend(str(w.message) for w in caught)
        return r

    def st_kg(r):
        m = r.measurements
        return f"{100 * m['stature']:.1f} cm, {m['mass']:.1f} kg"

    # requested bodies
    t = time.perf_counter()
    report("generating requested bodies", 0.05)
    requested, rows = [], []
    for i, (title, targets) in enumerate(REQUESTED):
        targets = {k: v for k, v in targets.items() if k in sm.labels_}
        r = run(sm.generate, targets, rng=seed + i)
        requested.append(r)
        rows.append({"request": title, "converged": r.converged, "iterations": r.iterations,
                     "measured": _cm_kg({k: r.measurements[k] for k in sm.measured_}),
                     **({"sex_model": round(r.values["sex"], 3)} if "sex" in r.values else {})})
    contact_sheet(np.array([r.vertices for r in requested]), faces, out / "requested.png",
                  labels=[f"asked {title}\nmeasured {st_kg(r)}" for (title, _), r in zip(REQUESTED, requested)],
                  title="requested bodies (closed loop: within 4 mm stature, 0.5 kg mass)")
    timings["semantic_requested_s"] = time.perf_counter() - t

    # taller, same weight
    t = time.perf_counter()
    report("morphing: taller, same weight", 0.15)
    base = requested[1]
    seq = [base] + [run(sm.morph, base.vertices, {"stature": d / 100.0}, keep=["mass"]) for d in TALLER_CM[1:]]
    contact_sheet(np.array([r.vertices for r in seq]), faces, out / "taller_same_weight.png",
                  labels=[f"+{d} cm\n{st_kg(r)}" for d, r in zip(TALLER_CM, seq)],
                  title="taller, same weight (morph with keep=mass)")
    taller = [{"change_cm": d, "measured": _cm_kg({k: r.measurements[k] for k in ("stature", "mass")}),
               "converged": r.converged} for d, r in zip(TALLER_CM, seq)]
    timings["semantic_taller_s"] = time.perf_counter() - t

    # masked morph: more muscular, upper body only
    t = time.perf_counter()
    report("morphing: more muscular, upper body only", 0.25)
    x0 = requested[0].vertices
    if "muscle" in sm.labels_:
        name = "muscle"
        y = sm.Y_[:, sm.labels_.index("muscle")]
        change = float(2.0 * np.nanstd(y))
    else:  # too few subjects to regress muscle: heavier instead
        name, change = "mass", 5.0
    if sm.regions_:
        mm = run(sm.morph, x0, {name: change}, mask="upper_body")
        w = sm.regions_["upper_body"]
        moved = np.linalg.norm(mm.vertices - x0, axis=1)
        outside = float(1000 * moved[w == 0].max()) if np.any(w == 0) else 0.0
    else:
        mm, outside = run(sm.morph, x0, {name: change}), float("nan")
        moved = np.linalg.norm(mm.vertices - x0, axis=1)
    contact_sheet(np.array([x0, mm.vertices]), faces, out / "muscle_upper_body.png", views=("front", "side"),
                  labels=[f"before\n{name} {mm.values[name] - change:.3g}",
                          f"{name} {change:+.3g}, upper body only\nmax move outside mask {outside:.2f} mm"],
                  title=f"masked morph: more {'muscular' if name == 'muscle' else 'mass'}, upper body only")
    masked = {"label": name, "change": change, "reached": round(float(mm.values[name]), 4),
              "max_displacement_inside_mm": round(float(1000 * moved.max()), 2),
              "max_displacement_outside_mm": round(outside, 4), "converged": mm.converged}
    timings["semantic_masked_morph_s"] = time.perf_counter() - t

    # a crowd
    t = time.perf_counter()
    report("generating a crowd", 0.35)
    k = CROWD if n_subj >= SEMANTIC_MIN_SUBJECTS else 4
    ask = {"sex": 0.0, "mass": 65.0, "stature": (1.55, 1.85)}
    ask = {a: v for a, v in ask.items() if a in sm.labels_}
    crowd = run(sm.crowd, k, ask, rng=seed)
    crowd_rows = []
    for i, r in enumerate(crowd):
        row = {"body": i, "converged": r.converged, "iterations": r.iterations}
        row.update(_cm_kg({m: r.measurements[m] for m in sm.measured_}))
        row.update({f"{lab} (model)": round(float(sm.regressors_[lab].predict(r.coefficients)), 3)
                    for lab in sm.labels_ if lab not in sm.measured_})
        crowd_rows.append(row)
    with atomic_path(out / "crowd.csv") as tmp, open(tmp, "w", newline="") as fh:
        wr = csv.DictWriter(fh, fieldnames=list(crowd_rows[0]))
        wr.writeheader()
        wr.writerows(crowd_rows)
    order = np.argsort([r.measurements["stature"] for r in crowd])
    contact_sheet(np.array([crowd[i].vertices for i in order]), faces, out / "crowd.png",
                  labels=[st_kg(crowd[i]) for i in order],
                  title=f"crowd of {k}: women of 65 kg, stature 155-185 cm")
    timings["semantic_crowd_s"] = time.perf_counter() - t

    # Hasler Table 1 and Hasler Table 2
    t = time.perf_counter()
    report("Table 1 and Table 2", 0.45)
    folds = min(10, n_subj)
    table1, table2 = sm.evaluate(folds=folds, rng=seed)
    unit = {"length": "cm", "mass": "kg", "age": "years", "percent": "%"}
    scale = np.array([100.0 if kind_of(n) == "length" else 1.0 for n in table1.labels])
    names = [f"{n} ({unit.get(kind_of(n), '1')})" for n in table1.labels]
    shown = RegressionTable(table1.regressors, names, table1.rmse * scale, table1.n_samples, table1.folds)
    with atomic_path(out / "semantic_tables.md") as tmp:
        tmp.write_text(
            f"# Semantic regressors (vertex encoding, {bm.n_components} components)\n\n"
            f"## Table 1: RMSE ({table1.folds}-fold cross-validation, {n_subj} subjects, each once)\n\n"
            f"{format_rmse_table(shown, markdown=True)}\n\n"
            f"## Table 2: angles between the non-linear model's morphing directions (degrees)\n\n"
            f"{format_angle_table(table2, markdown=True)}\n")
    timings["semantic_tables_s"] = time.perf_counter() - t

    # random-request study
    t = time.perf_counter()
    study_entry = {"skipped": f"{n_subj} subjects, fewer than {SEMANTIC_MIN_SUBJECTS}"}
    if n_subj >= SEMANTIC_MIN_SUBJECTS:
        report("random-request study", 0.55)
        study = request_study(sm, n=DEMO_REQUESTS, rng=seed, progress=lambda m, f: report(m, 0.55 + 0.45 * f))
        files = write_request_report(study, out)
        study_entry = {"n": study["n"], "joint_quantile": study["joint_quantile"],
                       "success_rate": study["success_rate"],
                       "errors": requests_in_display_units(study)["errors"],
                       "time_per_request_s": study["time_s"]["mean"], **files}
    timings["semantic_requests_s"] = time.perf_counter() - t

    return {
        "semantic": {"model": {"encoding": "vertex", "selection": "rest", "components": bm.n_components,
                               "labels": sm.labels_},
                     "requested": rows, "requested_png": "requested.png",
                     "taller_same_weight": taller, "masked_morph": masked,
                     "crowd": {"n": k, "asked": {a: list(v) if isinstance(v, tuple) else v for a, v in ask.items()},
                               "converged": int(sum(r.converged for r in crowd)), "csv": "crowd.csv"},
                     "tables": {"file": "semantic_tables.md", "folds": folds},
                     "requests": study_entry, "warnings": messages},
        "pictures": ["requested.png", "taller_same_weight.png", "muscle_upper_body.png", "crowd.png"],
    }


def mapping_demo(bm: BodyModel, out: Path, rng, timings: dict, report) -> dict:
    """Rupprecht's measurements-to-shape mapping on shape-only model ``bm``: a training set drawn
    from the model, the linear baseline, the linear-leaf forest and the exact refinement, scored on
    held-out requests (``mapping_tables.md``/``.json``, ``mapping_errors.png``) and the shoulder
    sweep (``shoulder_sweep.png``)."""
    t = time.perf_counter()
    small = bm.n_components < SEMANTIC_MIN_SUBJECTS  # a tiny database (the CLI test): a quick pass
    samples, held_out = (300, 30) if small else MAPPING_SIZES
    ev, _ = evaluate_mapping(bm, samples=samples, held_out=held_out, rng=rng, k=min(25, bm.n_components),
                             n_trees=10 if small else 50, progress=report)
    files = write_mapping_report(bm, ev, out)
    timings["mapping_s"] = time.perf_counter() - t
    variance = {m: {n: round(d["variance"], 4) for n, d in ev.table(m).items()} for m in ev.errors}
    return {
        "mapping": {"samples": samples, "held_out": held_out, "components": min(25, bm.n_components),
                    "variance_cm2": variance,
                    "within_1mm": {m: round(ev.within(m, 0.1), 4) for m in ev.errors},
                    "refine_ms_per_request": round(ev.timings["refine_ms_per_request"], 3),
                    "files": {k: Path(v).name for k, v in files.items()}},
        "pictures": [Path(files[k]).name for k in ("errors_png", "sweep_png") if k in files],
    }
