import json

import numpy as np
import pytest

from bodyspace.data.database import ScanDatabase
from bodyspace.errors import ParameterError
from bodyspace.measure.composition import (
    body_density,
    body_fat_percent,
    mass_from_volume,
)
from bodyspace.synth.population import build_population, load_survey, sample_subjects


def test_composition_formulas():
    # Deurenberg 1991: a 30-year-old man with BMI 25 has 1.2*25 + 0.23*30 - 10.8 - 5.4 = 20.7 %.
    assert body_fat_percent(25.0, 30.0, 1) == pytest.approx(20.7)
    # Siri: 0 % fat is 1.1 g/cm3; 100 % fat would be 0.9 g/cm3.
    assert body_density(0.0) == pytest.approx(1100.0)
    mass, bmi, bf = mass_from_volume(0.075, 1.75, 30.0, 1)
    assert mass == pytest.approx(0.075 * body_density(bf), rel=1e-9)
    assert bmi == pytest.approx(mass / 1.75**2)


def test_subjects_match_survey_moments(phenotype_model):
    subjects = sample_subjects(phenotype_model, 40, rng=3)
    survey = load_survey()
    assert np.abs(subjects.stature_m - subjects.target_stature_m).max() < 2e-4
    assert np.abs(subjects.bmi - subjects.target_bmi).max() < 1e-2
    for sex, male in (("male", True), ("female", False)):
        k = subjects.male == male
        assert k.sum() == 20
        assert abs(subjects.stature_m[k].mean() * 100 - survey[sex]["stature_mean"]) < 1.0
        assert abs(subjects.stature_m[k].std() * 100 - survey[sex]["stature_sd"]) < 1.0
        assert abs(subjects.bmi[k].mean() - survey[sex]["bmi_mean"]) < 0.5
        assert abs(subjects.bmi[k].std() - survey[sex]["bmi_sd"]) < 0.5
    assert (subjects.age_years >= 18).all() and (subjects.age_years <= 50).all()


def test_build_population_folder(template, tmp_path):
    out = tmp_path / "db"
    db = build_population(template, out, n_subjects=3, n_poses=2, rng=0)
    assert db.n_scans == 9 and db.n_subjects == 3
    assert set(p.name for p in out.iterdir()) >= {"vertices.npy", "faces.npy", "subjects.csv", "scans.csv",
                                                    "meta.json", "rotations.npy"}
    mm = np.load(out / "vertices.npy", mmap_mode="r")
    assert mm.dtype == np.float32 and mm.shape == (9, template.n_vertices, 3)
    meta = json.loads((out / "meta.json").read_text())
    assert meta["template"] == template.template_id and meta["format_version"] == 1
    assert "CC0" in meta["licence"] and "NATICK/TR-89/044" in meta["provenance"]["survey"]
    # Every scan stands on the ground; rest scans have identity rotations, posed ones do not.
    assert np.abs(mm[..., 1].min(axis=1)).max() < 1e-6
    rest = db.scans["pose"] == "rest"
    assert rest.sum() == 3
    assert np.abs(db.rotations[rest]).max() == 0 and np.abs(db.rotations[~rest]).max() > 0.1
    # Stature in the table is the rest mesh's.
    reloaded = ScanDatabase.load(out)
    st = np.ptp(np.asarray(reloaded.rest_pose().vertices)[..., 1], axis=1) * 100
    np.testing.assert_allclose(st, reloaded.subjects["stature_cm"], atol=1e-3)
    # Each subject's poses are distinct.
    for s in db.subjects["subject"]:
        poses = db.scans["pose"][db.scans["subject"] == s]
        assert len(set(poses)) == len(poses) == 3


def test_build_population_refuses_existing_and_bad_counts(template, tmp_path):
    with pytest.raises(ParameterError, match="subjects = 0"):
        build_population(template, tmp_path / "x", n_subjects=0, n_poses=1)
    (tmp_path / "y").mkdir()
    with pytest.raises(Exception, match="already exists"):
        build_population(template, tmp_path / "y", n_subjects=1, n_poses=0)
