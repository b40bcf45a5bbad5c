"""The user's labels are what the semantic regressors learn, small databases work or say why not,
every training subject is reachable, and generation never starts from an undefined body
(issue 12 §2, §4): on a 10-subject database of ours and on an imported foreign one."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from bodyspace.cli import app
from bodyspace.data.database import ScanDatabase
from bodyspace.errors import MeasurementError, ParameterError
from bodyspace.measure import evaluate as evaluate_measurements
from bodyspace.measure import load_landmarks, load_measurement_set, measurement_set_from_dict, with_landmarks
from bodyspace.measure.definitions import DEFAULT_PATH
from bodyspace.mesh.io import save_mesh
from bodyspace.model import BodyModel
from bodyspace.semantics.closed_loop import closed_loop
from bodyspace.semantics.evaluation import cross_validated_rmse, label_folds
from bodyspace.semantics.model import SemanticModel, tolerance
from bodyspace.synth import foreign as fo
from bodyspace.synth.population import build_population

N = 10
WAIST_OFFSET_CM = 2.0          # the "user's" waist tape reads 2 cm more than ours
MASS_UNKNOWN = (1, 4, 7)       # subjects whose mass the user did not weigh
HIP_GIVEN = (0, 5)             # the only subjects with a hip girth in the user's table
AGE_KNOWN = (0, 1, 2)          # too few ages to learn


@pytest.fixture(scope="module")
def small(template, tmp_path_factory):
    """10 subjects of ours with a user's subject table: stature_cm of all, mass_kg of 7, their own
    waist_girth_cm (+2 cm against our tape), thigh_girth_l_cm (a length of the set), hip_girth_cm
    of 2, age of 3 and a column no label uses; a shape-only vertex model with its regressors."""
    root = tmp_path_factory.mktemp("labels")
    population = build_population(template, root / "population", N, 0, rng=5)
    rest = population.rest_pose()
    tape = evaluate_measurements(load_measurement_set(), rest.read(np.arange(N)), rest.faces)
    subjects = dict(rest.subjects)
    subjects["mass_kg"] = np.where(np.isin(np.arange(N), MASS_UNKNOWN), np.nan, subjects["mass_kg"])
    subjects["waist_girth_cm"] = tape["waist_girth"].value * 100 + WAIST_OFFSET_CM
    subjects["thigh_girth_l_cm"] = tape["thigh_girth_l"].value * 100 + 1.0
    subjects["hip_girth_cm"] = np.where(np.isin(np.arange(N), HIP_GIVEN), tape["hip_girth"].value * 100 - 1.5, np.nan)
    subjects["age_years"] = np.where(np.isin(np.arange(N), AGE_KNOWN), subjects["age_years"], np.nan)
    subjects["foot_length_cm"] = np.full(N, 25.0)
    db = ScanDatabase(rest.vertices, rest.faces, subjects, rest.scans, rest.meta, rest.rotations).save(root / "db")
    db = ScanDatabase.load(db)
    model = BodyModel.fit(db, "vertex", "rest")
    sm = SemanticModel(model).fit(db, template=template)
    model.semantics = sm
    model.save(root / "model.npz")
    return root, db, model, sm, {name: m.value for name, m in tape.items()}


def test_the_users_labels_are_what_the_regressors_learn(small):
    _, db, _, sm, tape = small
    y = {name: sm.Y_[:, j] for j, name in enumerate(sm.labels_)}
    np.testing.assert_allclose(y["stature"], db.subjects["stature_cm"] / 100)
    weighed = ~np.isin(np.arange(N), MASS_UNKNOWN)
    np.testing.assert_allclose(y["mass"][weighed], db.subjects["mass_kg"][weighed])       # a weighed mass wins
    np.testing.assert_allclose(y["mass"][~weighed], tape["mass"][~weighed])               # the tape fills in
    np.testing.assert_allclose(y["waist_girth"], tape["waist_girth"] + WAIST_OFFSET_CM / 100)
    # the regressor learned the user's waist: through the mean of the user's values, not ours
    waist = sm.regressor("waist_girth").predict(sm.X_)
    assert abs(waist.mean() - (tape["waist_girth"].mean() + 0.02)) < 1e-3
    # a length of the set the user gives is a label, measured on bodies
    assert "thigh_girth_l" in sm.labels_ and "thigh_girth_l" in sm.measured_ and "thigh_girth_l" not in sm.lengths_
    np.testing.assert_allclose(y["hip_girth"][list(HIP_GIVEN)], tape["hip_girth"][list(HIP_GIVEN)] - 0.015)
    p = sm.provenance_
    assert (p["stature"]["from_labels"], p["stature"]["measured"]) == (N, 0)
    assert (p["mass"]["from_labels"], p["mass"]["measured"], p["mass"]["column"]) == (7, 3, "mass_kg")
    assert (p["hip_girth"]["from_labels"], p["hip_girth"]["measured"]) == (2, 8)
    assert (p["chest_girth"]["from_labels"], p["chest_girth"]["measured"]) == (0, N)
    assert p["waist_girth"]["tape_vs_labels"]["n"] == N
    assert abs(p["waist_girth"]["tape_vs_labels"]["mean"] + WAIST_OFFSET_CM / 100) < 1e-9
    assert "age" not in sm.labels_ and "known on 3 of 10 subjects, at least 4 needed" in sm.skipped_["age"]
    with pytest.raises(ParameterError, match="age: not learned from the database: known on 3 of 10"):
        sm.regressor("age")
    assert "foot_length_cm" in sm.unused_columns_ and "stature_cm" not in sm.unused_columns_


def test_provenance_is_stored_with_the_model(small):
    root, _, _, sm, _ = small
    loaded = BodyModel.load(root / "model.npz").semantics
    assert loaded.provenance_ == json.loads(json.dumps(sm.provenance_))
    assert loaded.skipped_ == sm.skipped_ and loaded.unused_columns_ == sm.unused_columns_
    assert loaded.spans_ == pytest.approx(sm.spans_)
    assert loaded.reachable_range("stature") == sm.reachable_range("stature")


def test_evaluate_says_where_each_label_came_from(small, tmp_path):
    root, _, _, _, _ = small
    result = CliRunner().invoke(app, ["evaluate", str(root / "model.npz"), "--out", str(tmp_path / "ev.md")])
    assert result.exit_code == 0, result.output
    text = " ".join(result.output.split())
    for line in ("stature: subjects.csv column stature_cm (10 of 10 subjects)",
                 "mass: subjects.csv column mass_kg 7, measured on the rest scans 3 (of 10 subjects)",
                 "waist_girth: subjects.csv column waist_girth_cm (10 of 10 subjects); tape on the rest scans - "
                 "subjects.csv: mean -2.0 cm",
                 "chest_girth: measured on the rest scans (10 of 10 subjects)",
                 "hip_girth: subjects.csv column hip_girth_cm 2, measured on the rest scans 8 (of 10 subjects)",
                 "age: not learned: known on 3 of 10 subjects, at least 4 needed",
                 "no label uses:", "foot_length_cm",
                 "Table 1: RMSE, leave-one-out cross-validation (10 folds), 10 subjects once each"):
        assert line in text, (line, text)
    report = json.loads((tmp_path / "ev.json").read_text())
    assert report["labels"]["provenance"]["mass"]["measured"] == 3
    assert report["table1"]["label_folds"]["thigh_girth_l"] == N
    assert "hip_girth: subjects.csv column hip_girth_cm 2" in (tmp_path / "ev.md").read_text()


def test_cross_validation_with_few_known_values():
    """10 rows, a label known on 4 (what failed with 'X: 1 row(s), expected at least 2'):
    leave-one-out over the known rows; 3 known values are refused with the minimum."""
    rng = np.random.default_rng(0)
    x = rng.normal(size=(N, 5))
    y = x @ rng.normal(size=5) + 0.1 * rng.normal(size=N)
    few = np.where(np.arange(N) < 4, y, np.nan)
    table = cross_validated_rmse(x, {"all": y, "few": few}, folds=10, rng=0)
    assert table.label_folds.tolist() == [10, 4] and table.n_samples.tolist() == [10, 4]
    assert np.isfinite(table.rmse).all()
    assert [label_folds(n, 10) for n in (4, 5, 6, 12, 40)] == [4, 5, 6, 10, 10]
    assert label_folds(6, 2) == 2          # 2 folds of 6 train on 3 rows: enough
    assert label_folds(5, 2) == 5          # 2 folds of 5 would train on 2: leave-one-out
    with pytest.raises(ParameterError, match=r"labels\['few'\]: 3 known value\(s\), expected at least 4"):
        cross_validated_rmse(x, {"few": np.where(np.arange(N) < 3, y, np.nan)}, folds=5)
    grouped = cross_validated_rmse(np.repeat(x, 2, axis=0), {"few": np.repeat(few, 2)}, folds=10, rng=0,
                                   groups=np.repeat(np.arange(N), 2))
    assert grouped.label_folds.tolist() == [4] and grouped.n_samples.tolist() == [8]


def test_a_small_database_evaluates_or_says_the_minimum(small, template):
    _, db, model, sm, _ = small
    table1, table2 = sm.evaluate(folds=10, rng=0)
    assert np.isfinite(table1.rmse).all() and set(table2) == set(sm.labels_)
    three = db.select(np.flatnonzero(np.isin(db.scans["subject"], db.subjects["subject"][:3])))
    with pytest.raises(ParameterError, match="3 subjects, expected at least 4"):
        SemanticModel(BodyModel.fit(three, "vertex", "rest")).fit(three, template=template)


def test_every_training_subject_is_reachable(small):
    """With a narrow sigma_limit the regressors' own range leaves the extreme subjects out; the
    reachable range widens to them, the closed loop reaches the tallest subject's stature and
    the exact refinement a subject's extreme waist_size (its box admits every subject)."""
    _, _, model, sm, tape = small
    narrow = SemanticModel.from_arrays(sm.to_arrays(), model, sigma_limit=1.0)
    for j, name in enumerate(narrow.labels_):
        lo, hi = narrow.reachable_range(name)
        known = narrow.Y_[:, j][np.isfinite(narrow.Y_[:, j])]
        assert lo <= known.min() and hi >= known.max(), (name, lo, hi, known.min(), known.max())
    lo, hi = narrow.reachable_range("waist_size")
    assert lo <= tape["waist_size"].min() and hi >= tape["waist_size"].max()
    z = np.abs(narrow.X_) / np.sqrt(narrow.variances)
    assert narrow.coefficient_bound == pytest.approx(z.max()) and narrow.coefficient_bound > 1.0
    tallest = float(narrow.Y_[:, narrow.labels_.index("stature")].max())
    result = narrow.generate({"stature": tallest}, rng=0)
    assert result.converged and abs(result.values["stature"] - tallest) <= tolerance("stature")
    model.semantics = narrow
    try:
        widest = float(tape["waist_size"].max())
        refined = model.generate({"waist_size": widest}, rng=0)
        assert refined.converged and abs(refined.values["waist_size"] - widest) <= 0.001
    finally:
        model.semantics = sm


def _upright_within(degrees: float):
    """The default measurement set with the 'upright' condition at ``degrees`` (12 in the set) and
    'head_level' at ``degrees`` + 5 (35 in the set): our bodies' head axis leans ~14 degrees from
    the torso's, so 9 leaves part of the random bodies without a stature and 1 every body."""
    definition = json.loads(DEFAULT_PATH.read_text())
    definition["conditions"]["upright"]["max_angle_deg"] = degrees
    definition["conditions"]["head_level"]["max_angle_deg"] = degrees + 5
    return measurement_set_from_dict(definition, f"hm08 with upright at {degrees} degrees")


class _SetSemantics(SemanticModel):
    """A SemanticModel measuring with another measurement set (the model's own regressors)."""

    other_set = None

    @property
    def mset(self):
        return self.other_set


def _with_set(sm, model, mset):
    copy = _SetSemantics.from_arrays(sm.to_arrays(), model)
    copy.other_set = mset
    return copy


def test_generation_starts_where_the_asked_measurement_is_defined(small):
    _, _, model, sm, _ = small
    picky = _with_set(sm, model, _upright_within(9.0))
    # a seed whose first random body has no stature under this set
    seed = next(s for s in range(40) if not np.isfinite(evaluate_measurements(
        picky.mset, model.reconstruct(model.sample_coefficients(1, sigma_range=2.0, rng=np.random.default_rng(s)))[0],
        model.faces)["stature"].value))
    first = model.sample_coefficients(1, sigma_range=2.0, rng=np.random.default_rng(seed))[0]
    result = picky.generate({"stature": 1.70}, rng=seed)
    assert result.converged and np.isfinite(result.vertices).all()
    assert abs(result.values["stature"] - 1.70) <= tolerance("stature")
    assert not np.allclose(result.start, first)      # it started elsewhere


def test_no_defined_start_is_refused_with_the_reason(small):
    _, db, model, sm, _ = small
    never = _with_set(sm, model, _upright_within(1.0))
    with pytest.raises(MeasurementError, match=r"generate: stature not defined on this model's bodies: 8 random "
                                               r"bodies and the mean body measure no value \(stature: not upright"):
        never.generate({"stature": 1.70, "sex": 1.0}, rng=0)
    with pytest.raises(MeasurementError, match=r"the body to morph: stature not defined \(stature: not upright"):
        never.morph(db.mesh(0), {"stature": 0.03})
    # sex alone needs no measurement: fine
    assert never.generate({"sex": 1.0}, rng=0).converged


def test_closed_loop_refuses_an_undefined_start():
    with pytest.raises(ParameterError, match="closed_loop: the start body's values .* not all finite"):
        closed_loop(np.zeros(3), [1.0], [0.01], np.ones(3), np.ones((1, 3)), lambda c: np.zeros((4, 3)),
                    lambda x, c: (np.array([np.nan]), {}))


# -- an imported foreign database: labels.csv, provenance, small, reachable -----------------------

class _ForeignSemantics(_SetSemantics):
    """The foreign topology's measurement set (its landmark file) until models carry their own."""

    def __init__(self, body_model, other_set, **params):
        super().__init__(body_model, **params)
        self.other_set = other_set


def test_foreign_import_labels_and_generation(template, phenotype_model, tmp_path):
    """6 subjects x (rest, t_pose) of a 4,000-vertex topology in mm, Z up, imported with a labels
    CSV (stature of all, mass of 4): the regressors learn the CSV's values, evaluate splits
    leave-one-out, and the tallest subject's stature is reachable and generated."""
    rng = np.random.default_rng(21)
    topology = fo.foreign_topology(template, 4000, rng)
    folder = tmp_path / "scans"
    folder.mkdir()
    rows = []
    for s in range(6):
        phenotype = None
        for pose in ("rest", "t_pose"):
            body = fo.foreign_body(template, phenotype_model, topology, rng, phenotype=phenotype, pose=pose)
            phenotype = body.phenotype
            save_mesh(folder / f"s{s}_{pose}.obj", body.vertices, body.faces)
            mass = "" if s in (2, 4) else f"{60 + 5 * s}"
            rows.append(f"s{s}_{pose}.obj,s{s},{pose},{155 + 5 * s},{mass}")
    (folder / "labels.csv").write_text("mesh,subject,pose,stature_cm,mass_kg\n" + "\n".join(rows) + "\n")
    (tmp_path / "landmarks.json").write_text(json.dumps(topology.landmark_file()))
    result = CliRunner().invoke(app, ["import", str(folder), "--labels", str(folder / "labels.csv"), "--out",
                                      str(tmp_path / "db"), "--units", "mm", "--up", "z"])
    assert result.exit_code == 0, result.output
    db = ScanDatabase.load(tmp_path / "db")
    landmarks, n = load_landmarks(tmp_path / "landmarks.json")
    mset = with_landmarks(load_measurement_set(), landmarks, n)
    model = BodyModel.fit(db, "vertex", "rest")
    sm = _ForeignSemantics(model, mset).fit(db)
    assert sm.provenance_["stature"]["source"] == "labels.csv"
    assert (sm.provenance_["mass"]["from_labels"], sm.provenance_["mass"]["measured"]) == (4, 2)
    np.testing.assert_allclose(sm.Y_[:, sm.labels_.index("stature")], [1.55, 1.60, 1.65, 1.70, 1.75, 1.80])
    table1, _ = sm.evaluate(folds=6, rng=0)
    assert (table1.label_folds == 6).all() and np.isfinite(table1.rmse).all()
    lo, hi = sm.reachable_range("stature")
    assert lo <= 1.55 and hi >= 1.80
    result = sm.generate({"stature": 1.80}, rng=1)
    assert result.converged and abs(result.values["stature"] - 1.80) <= tolerance("stature")


def test_label_columns_names_and_aliases():
    from bodyspace.semantics.labels import label_columns
    mset = load_measurement_set()
    assert label_columns(mset, ["height_cm", "weight_kg", "waist_size_cm", "volume_m3", "bmi_kg_m2"]) == {
        "stature": "height_cm", "waist_size": "waist_size_cm", "mass": "weight_kg"}
    # each column gives one label; a measurement's own name wins over an alias
    assert label_columns(mset, ["height_cm", "stature_cm", "mass_kg", "weight_kg"]) == {
        "stature": "stature_cm", "height": "height_cm", "mass": "mass_kg"}
