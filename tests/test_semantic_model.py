"""SemanticModel: closed-loop generation, morphing with keep and masks, units, CLI."""

import csv
import json
import warnings

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from bodyspace.cli.semantics import crowd, evaluate, generate, morph
from bodyspace.errors import SemanticsFileError
from bodyspace.measure import measure
from bodyspace.mesh.io import load_mesh
from bodyspace.model import BodyModel, ModelError
from bodyspace.register.detail import Detail, apply_detail, faces_digest, load_detail, midpoint_subdivide, save_detail
from bodyspace.report.semantic_report import format_request_report, write_request_report
from bodyspace.semantics.masks import MaskedPoissonBlend
from bodyspace.semantics.model import SemanticModel, TargetError, tolerance
from bodyspace.studies.requests import request_study
from bodyspace.synth.population import build_population
from bodyspace.units import UnitError, kind_of, parse_assignment, parse_target


@pytest.fixture(scope="session")
def setup(template, tmp_path_factory):
    root = tmp_path_factory.mktemp("semantic")
    db = build_population(template, root / "db", 24, 0, rng=0)
    model = BodyModel.fit(db, "vertex", "rest")
    model.save(root / "model.npz")
    sm = SemanticModel(model).fit(db, template=template)
    model.semantics = sm
    model.save(root / "model.npz")
    return root, db, model, sm


def _check(result):
    for name, goal in result.targets.items():
        assert abs(result.values[name] - goal) <= tolerance(name), (name, result.values[name], goal)


@pytest.mark.parametrize("targets", [
    {"stature": 1.80, "mass": 80.0},
    {"stature": 1.62, "mass": 55.0, "waist_girth": 0.72},
    {"sex": 0.0, "mass": 65.0, "stature": (1.55, 1.85)},
])
def test_generate_measures_what_was_asked(setup, targets):
    _, _, model, sm = setup
    result = sm.generate(targets, rng=3)
    assert result.converged
    _check(result)
    # the reached values are what a tape measure reads on the mesh
    m = measure(sm.mset, result.vertices, model.faces)
    for name in ("stature", "mass"):
        if name in targets and not isinstance(targets[name], tuple):
            assert abs(m[name] - targets[name]) <= tolerance(name)
    if "stature" in targets and isinstance(targets["stature"], tuple):
        assert 1.55 <= m["stature"] <= 1.85


def test_infeasible_refused_with_range_or_clamped(setup):
    _, _, model, sm = setup
    lo, hi = sm.reachable_range("stature")
    with pytest.raises(TargetError, match=r"outside what the model can reach \(\d+\.\d cm to \d+\.\d cm"
                                          r".*--clamp on the command line, on_infeasible='clamp' in Python"):
        sm.generate({"stature": 2.6})
    clamping = BodyModel.load(setup[0] / "model.npz").semantics.set_params(on_infeasible="clamp")
    with pytest.warns(RuntimeWarning, match="clamped to"):
        result = clamping.generate({"stature": 2.6}, rng=0)
    assert result.targets["stature"] == pytest.approx(hi)
    assert any("clamped" in m for m in result.messages)


def test_taller_same_mass(setup):
    _, _, model, sm = setup
    x0 = model.reconstruct(model.sample_coefficients(1, sigma_range=1.0, rng=5))[0]
    before = measure(sm.mset, x0, model.faces)
    result = sm.morph(x0, {"stature": 0.05}, keep=["mass"])
    after = measure(sm.mset, result.vertices, model.faces)
    assert abs(after["stature"] - before["stature"] - 0.05) <= 0.004
    assert abs(after["mass"] - before["mass"]) <= 0.5


def test_morph_of_a_turned_body_is_the_morph_turned(setup):
    # A registration keeps the scan's turn about the vertical; the change must turn with the body
    # (it was added in the model's frame: a 30° turned body grew its belly 30° off).
    _, _, model, sm = setup
    x0 = model.reconstruct(model.sample_coefficients(1, sigma_range=1.0, rng=5))[0]
    a = np.radians(30.0)
    R = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    shift = np.array([0.3, -0.8, 0.1])
    straight = sm.morph(x0, {"mass": 5.0})
    turned = sm.morph(x0 @ R.T + shift, {"mass": 5.0})
    expected = straight.vertices @ R.T + shift
    assert np.abs(turned.vertices - expected).max() < 1e-3
    assert abs(turned.values["mass"] - straight.values["mass"]) < 0.05


@pytest.mark.parametrize("region", ["upper_body", "legs", "left"])
def test_masked_morph_keeps_outside(setup, region):
    _, _, model, sm = setup
    x0 = model.reconstruct(model.sample_coefficients(1, sigma_range=1.0, rng=7))[0]
    result = sm.morph(x0, {"mass": 4.0}, mask=region)
    w = sm.regions_[region]
    moved = np.linalg.norm(result.vertices - x0, axis=1)
    assert moved[w == 0].max() < 0.002
    assert moved[w == 1].max() > 0.005           # inside it did change
    assert abs(result.values["mass"] - result.targets["mass"]) <= 0.5
    # no step at the seam: along edges, the change varies no more there than inside the mask
    e = np.unique(np.sort(model.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)
    jump = np.linalg.norm((result.vertices - x0)[e[:, 0]] - (result.vertices - x0)[e[:, 1]], axis=1)
    seam = (w[e[:, 0]] == 0) != (w[e[:, 1]] == 0)
    inside = (w[e[:, 0]] == 1) & (w[e[:, 1]] == 1)
    assert jump[seam].max() < 3 * np.percentile(jump[inside], 99)


def test_masked_blend_identity_and_zero(setup):
    _, _, model, sm = setup
    x0 = model.mean_vertices
    d = np.random.default_rng(0).normal(size=x0.shape) * 1e-3
    w = sm.regions_["arms"]
    out = MaskedPoissonBlend(x0, model.faces, w)(d)
    assert np.all(out[w == 0] == 0)
    np.testing.assert_allclose(MaskedPoissonBlend(x0, model.faces, np.ones(len(x0)))(d), d)
    with pytest.raises(Exception, match="every weight is 0"):
        MaskedPoissonBlend(x0, model.faces, np.zeros(len(x0)))


def test_regressors_saved_in_the_model_file_bit_exact(setup):
    root, _, model, sm = setup
    loaded = BodyModel.load(root / "model.npz")
    sm2 = loaded.semantics
    assert sm2 is not None and sm2.body_model is loaded
    assert not (root / "model.semantics.npz").exists()  # one file, nothing beside it
    c = model.sample_coefficients(3, rng=1)
    assert sm2.labels_ == sm.labels_ and sm2.lengths_ == sm.lengths_ and sm2.measured_ == sm.measured_
    for name, reg in sm.regressors_.items():
        assert np.array_equal(sm2.regressors_[name].predict(c), reg.predict(c)), name
        assert np.array_equal(sm2.regressors_[name].gradient(c[0]), reg.gradient(c[0])), name
    assert sm2.reachable_range("mass") == sm.reachable_range("mass")
    assert np.array_equal(sm2.X_, sm.X_) and np.array_equal(sm2.Y_, sm.Y_, equal_nan=True)
    assert np.array_equal(sm2.regions_["legs"], sm.regions_["legs"])
    # the same request gives the same body from the fitted and the loaded regressors
    a, b = sm.generate({"stature": 1.75, "mass": 70.0}, rng=4), sm2.generate({"stature": 1.75, "mass": 70.0}, rng=4)
    assert np.array_equal(a.coefficients, b.coefficients)
    # a model file without semantics stays loadable and has none
    loaded.semantics = None
    loaded.save(root / "plain.npz")
    assert BodyModel.load(root / "plain.npz").semantics is None


def test_units():
    assert parse_target("stature", "180cm").value == pytest.approx(1.8)
    assert parse_target("stature", "1.8m").value == pytest.approx(1.8)
    assert parse_target("weight", "80kg").name == "mass"
    t = parse_target("stature", "+5cm")
    assert (t.kind, t.value) == ("delta", pytest.approx(0.05))
    assert parse_target("sex", "female").value == 0.0
    r = parse_assignment("stature=155:185cm")
    assert (r.kind, r.lo, r.hi) == ("range", pytest.approx(1.55), pytest.approx(1.85))
    with pytest.raises(UnitError, match=r"stature: '180' has no unit; expected one of cm, m"):
        parse_target("stature", "180")
    with pytest.raises(UnitError, match="not a length unit"):
        parse_target("stature", "80kg")
    with pytest.raises(UnitError, match="mass: unit 'cm'.*not a mass unit; expected one of kg"):
        parse_target("mass", "80cm")
    with pytest.raises(UnitError, match="expected male or female"):
        parse_target("sex", "x")
    with pytest.raises(UnitError, match="NAME=VALUE"):
        parse_assignment("stature180cm")
    with pytest.raises(UnitError, match="low >= high"):
        parse_target("stature", "185:155cm")


@pytest.fixture(scope="module")
def app():
    a = typer.Typer()
    for f in (evaluate, generate, morph, crowd):
        a.command(f.__name__)(f)
    return a


def test_cli_generate_and_morph(setup, app, tmp_path):
    root, _, model, sm = setup
    runner = CliRunner()
    r = runner.invoke(app, ["generate", str(root / "model.npz"), "--set", "stature=180cm", "--set", "mass=80kg",
                            "--set", "sex=male", "--out", str(tmp_path / "a.obj")])
    assert r.exit_code == 0, r.output
    v, f = load_mesh(tmp_path / "a.obj")
    m = measure(sm.mset, v, f)
    assert abs(m["stature"] - 1.80) <= 0.0045 and abs(m["mass"] - 80) <= 0.55
    r = runner.invoke(app, ["morph", str(root / "model.npz"), str(tmp_path / "a.obj"), "--set", "stature=+5cm",
                            "--keep", "mass", "--mask", "upper_body", "--out", str(tmp_path / "b.obj")])
    assert r.exit_code == 0, r.output
    v2, _ = load_mesh(tmp_path / "b.obj")
    w = sm.regions_["upper_body"]
    assert np.linalg.norm(v2 - v, axis=1)[w == 0].max() < 0.002
    # --detail: a relief (here 1 mm outward everywhere, 2 mm on the first vertices) re-added on the morph
    sub, _ = midpoint_subdivide(v, f, 1)
    offsets = np.full(len(sub), 0.001)
    offsets[:100] = 0.002
    save_detail(tmp_path / "detail.npz", Detail(offsets, np.ones(len(sub), bool), 1, len(v), len(f), faces_digest(f)))
    r = runner.invoke(app, ["morph", str(root / "model.npz"), str(tmp_path / "a.obj"), "--set", "stature=+5cm",
                            "--keep", "mass", "--mask", "upper_body", "--detail", str(tmp_path / "detail.npz"),
                            "--out", str(tmp_path / "b_detail.obj")])
    assert r.exit_code == 0, r.output
    vd, fd = load_mesh(tmp_path / "b_detail.obj")
    want, want_faces = apply_detail(v2, f, load_detail(tmp_path / "detail.npz"))
    assert np.array_equal(fd, want_faces) and np.abs(vd - want).max() < 1e-5
    r = runner.invoke(app, ["morph", str(root / "model.npz"), str(tmp_path / "a.obj"), "--set", "stature=+5cm",
                            "--detail", str(tmp_path / "a.obj"), "--out", str(tmp_path / "b_bad.obj")])
    assert r.exit_code == 2 and "bodyspace register --detail" in " ".join(r.output.split())
    r = runner.invoke(app, ["generate", str(root / "model.npz"), "--set", "stature=260cm", "--out",
                            str(tmp_path / "c.obj")])
    assert r.exit_code == 2 and "can reach" in r.output and "cm to" in r.output
    r = runner.invoke(app, ["generate", str(root / "model.npz"), "--set", "stature=260cm", "--clamp", "--out",
                            str(tmp_path / "c.obj")])
    assert r.exit_code == 0 and "clamped" in r.output
    r = runner.invoke(app, ["generate", str(root / "model.npz"), "--set", "stature=180", "--out",
                            str(tmp_path / "d.obj")])
    assert r.exit_code == 2 and "no unit" in r.output


def test_cli_morph_of_a_posed_body_is_morphed_standing(setup, app, tmp_path, template):
    # A T-posed registered scan: the change is the standing body's, posed back (it was added to the
    # posed mesh in the rest pose's directions and measured on the posed mesh)
    root, _, model, sm = setup
    from bodyspace.mesh.io import save_mesh
    from bodyspace.rig.posing import pose_bodies
    from bodyspace.rig.unpose import unpose
    from bodyspace.synth.poses import load_pose_library
    rig = template.rigs["default"]
    x0 = model.reconstruct(model.sample_coefficients(1, sigma_range=1.0, rng=5))[0]
    R = load_pose_library().rotations("t_pose", rig)
    save_mesh(tmp_path / "posed.obj", pose_bodies(x0, rig, R, on_ground=True), model.faces)
    r = CliRunner().invoke(app, ["morph", str(root / "model.npz"), str(tmp_path / "posed.obj"), "--set", "mass=+5kg",
                                 "--out", str(tmp_path / "heavier.obj")])
    assert r.exit_code == 0, r.output
    assert "morphed standing" in r.output
    posed_in, f = load_mesh(tmp_path / "posed.obj")
    out, _ = load_mesh(tmp_path / "heavier.obj")
    before = measure(sm.mset, unpose(posed_in, rig)[0], f)["mass"]
    after = measure(sm.mset, unpose(out, rig)[0], f)["mass"]
    assert abs(after - before - 5.0) <= 0.55, (before, after)
    # the arms' change follows the arms: the posed output is the standing morph posed
    expected = pose_bodies(sm.morph(x0, {"mass": 5.0}).vertices, rig, R, on_ground=True)
    err = np.linalg.norm(out - expected - (out - expected).mean(axis=0), axis=1)   # up to where it stands
    assert np.percentile(err, 95) < 0.003, np.percentile(err, 95)


def test_cli_crowd_and_evaluate(setup, app, tmp_path):
    root, db, _, _ = setup
    runner = CliRunner()
    r = runner.invoke(app, ["crowd", str(root / "model.npz"), "-n", "4", "--set", "sex=female", "--set", "mass=65kg",
                            "--range", "stature=155:185cm", "--out", str(tmp_path / "crowd")])
    assert r.exit_code == 0, r.output
    rows = list(csv.DictReader(open(tmp_path / "crowd" / "crowd.csv")))
    assert len(rows) == 4 and (tmp_path / "crowd" / "lineup.png").stat().st_size > 0
    for row in rows:
        assert abs(float(row["mass (kg)"]) - 65) <= 0.5
        assert 155 <= float(row["stature (cm)"]) <= 185
    # evaluate fits the regressors from --database when asked to
    copy = tmp_path / "m.npz"
    plain = BodyModel.load(root / "model.npz")
    plain.semantics = None
    plain.save(copy)
    r = runner.invoke(app, ["evaluate", str(copy), "--folds", "3"])
    assert r.exit_code == 2 and "--database" in r.output
    r = runner.invoke(app, ["evaluate", str(copy), "--database", str(root / "db"), "--folds", "3"])
    assert r.exit_code == 0, r.output
    assert "saved the semantic regressors into" in r.output
    assert BodyModel.load(copy).semantics is not None and not (tmp_path / "m.semantics.npz").exists()
    text = (tmp_path / "m.evaluation.md").read_text()
    assert "filtered linear" in text and "non-linear" in text and "μ" in text and "stature (cm)" in text


def test_request_study_small(setup, tmp_path):

    _, _, _, sm = setup
    study = request_study(sm, n=40, rng=0)
    assert study["n"] == 40 and study["success_rate"] == 1.0, study["failures"]
    for name, (lo, hi) in study["box"].items():
        asked = np.array([r["asked"][name] for r in study["requests"]])
        assert lo <= asked.min() and asked.max() <= hi
    assert study["errors"]["stature"]["max"] <= 0.004 and study["errors"]["mass"]["max"] <= 0.5
    assert study["errors"]["waist_girth"]["unit"] == "m" and study["errors"]["waist_girth"]["max"] <= 0.009
    assert sm.mset.names == tuple(m["name"] for m in sm.mset.measurements) and len(sm.mset.names) > 5
    files = write_request_report(study, tmp_path)
    assert "40/40" in (tmp_path / files["md"]).read_text()
    written = json.loads((tmp_path / files["json"]).read_text())
    assert written["successes"] == 40 and written["errors"]["waist_girth"]["unit"] == "mm"
    assert np.isclose(written["errors"]["waist_girth"]["max"], 1000 * study["errors"]["waist_girth"]["max"])


def test_request_study_independent_draws_never_miss_silently(setup):
    """Box corners no subject has may be missed, but never silently, and every request inside
    the population's joint 98% region lands."""
    _, _, _, sm = setup
    study = request_study(sm, n=30, rng=5, joint=None)
    split = study["by_plausibility"]
    assert split["inside"]["n"] + split["outside"]["n"] == 30
    assert split["inside"]["successes"] == split["inside"]["n"]
    assert study["silent_misses"] == 0
    assert all(f["explained"] and "not" in f["message"] for f in study["failures"])
    assert all(0.0 <= r["population_quantile"] <= 1.0 for r in study["requests"])
    assert "Inside and outside the population" in format_request_report(study)


def test_generate_measurement_targets(setup, app, tmp_path):
    """Any length of the measurement set is a target: a Rupprecht loop and an ISO width."""
    root, _, model, sm = setup
    assert {"waist_size", "shoulder_width", "thigh_girth_l", "height"} <= set(sm.lengths_)
    assert all(kind_of(n) == "length" for n in sm.lengths_)
    lo, hi = sm.reachable_range("waist_size")
    lo2, hi2 = sm.reachable_range("shoulder_width")
    goal = {"waist_size": lo + 0.45 * (hi - lo), "shoulder_width": lo2 + 0.55 * (hi2 - lo2)}
    result = sm.generate(goal, rng=2)
    assert result.converged
    m = measure(sm.mset, result.vertices, model.faces)
    for name, v in goal.items():
        assert abs(m[name] - v) <= 0.009, (name, m[name], v)
    assert set(sm.measured_) <= set(result.measurements)
    # only what was asked is measured in the loop: the small subset, not the whole set
    assert "thigh_girth_l" not in result.measurements
    with pytest.raises(Exception, match="accepted names.*waist_size"):
        sm.generate({"waist_sizes": 0.8})
    runner = CliRunner()
    w = 0.5 * (lo + hi)
    r = runner.invoke(app, ["generate", str(root / "model.npz"), "--set", f"waist_size={100 * w:.1f}cm",
                            "--out", str(tmp_path / "w.obj")])
    assert r.exit_code == 0, r.output
    v, f = load_mesh(tmp_path / "w.obj")
    assert abs(measure(sm.mset, v, f)["waist_size"] - round(w, 3)) <= 0.0095
    r = runner.invoke(app, ["generate", str(root / "model.npz"), "--set", "waist_sizes=80cm",
                            "--out", str(tmp_path / "x.obj")])
    assert r.exit_code == 2 and "accepted names" in r.output and "shoulder_width" in r.output


# ----------------------------------------------------------------------------------- storage
def _write_legacy_sidecar(sm, path):
    """``MODEL.semantics.npz`` exactly as ``SemanticModel.save`` wrote it before the regressors
    moved into the model file (format_version 1)."""
    arrays = {"X": sm.X_, "Y": sm.Y_, "subjects": np.array(sm.subjects_, dtype="U")}
    regs = {}
    for name, reg in sm.regressors_.items():
        regs[name] = type(reg).__name__
        for k, a in reg.to_arrays().items():
            arrays[f"reg/{name}/{k}"] = a
    for name, w in sm.regions_.items():
        arrays[f"region/{name}"] = w.astype(np.float32)
    header = {"format": "bodyspace.SemanticModel", "format_version": 1, "labels": sm.labels_,
              "measured": sm.measured_, "lengths": sm.lengths_, "regressors": regs, "regions": list(sm.regions_),
              "sigma_limit": sm.sigma_limit, "n_components": int(sm.X_.shape[1]),
              "template_id": sm.body_model.template_id, "units": {}}
    arrays["header"] = np.frombuffer(json.dumps(header).encode("utf-8"), dtype=np.uint8)
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)


def _plain_copy(root, path):
    plain = BodyModel.load(root / "model.npz")
    plain.semantics = None
    plain.save(path)
    return path


def test_legacy_sidecar_folded_into_the_model_file(setup, app, tmp_path):
    root, _, _, sm = setup
    model_file = _plain_copy(root, tmp_path / "old.npz")
    sidecar = tmp_path / "old.semantics.npz"
    _write_legacy_sidecar(sm, sidecar)
    before = sidecar.read_bytes()
    runner = CliRunner()
    args = ["generate", str(model_file), "--set", "stature=175cm", "--out", str(tmp_path / "a.obj")]
    r = runner.invoke(app, args)
    assert r.exit_code == 0, r.output
    assert "note: folded" in r.output and "old.semantics.npz" in r.output
    assert sidecar.read_bytes() == before  # left as it was
    folded = BodyModel.load(model_file).semantics
    c = sm.body_model.sample_coefficients(2, rng=3)
    for name, reg in sm.regressors_.items():
        assert np.array_equal(folded.regressors_[name].predict(c), reg.predict(c)), name
    np.testing.assert_allclose(folded.regions_["legs"], sm.regions_["legs"], atol=1e-7)
    # read once: the next run uses the model file and says nothing about the sidecar
    r = runner.invoke(app, args[:-1] + [str(tmp_path / "b.obj")])
    assert r.exit_code == 0 and "note: folded" not in r.output, r.output


@pytest.mark.parametrize("damage", ["garbage", "truncated", "no_header", "other_model"])
def test_damaged_sidecar_refused_clearly(setup, app, tmp_path, damage):
    root, _, model, sm = setup
    model_file = _plain_copy(root, tmp_path / "m.npz")
    sidecar = tmp_path / "m.semantics.npz"
    _write_legacy_sidecar(sm, sidecar)
    data = sidecar.read_bytes()
    if damage == "garbage":
        sidecar.write_bytes(b"not an npz at all")
    elif damage == "truncated":
        sidecar.write_bytes(data[: len(data) // 2])
    elif damage == "no_header":
        with np.load(sidecar) as z:
            arrays = {k: z[k] for k in z.files if k != "header"}
        np.savez(sidecar, **arrays)
    else:  # fitted on a model with another number of components
        with np.load(sidecar) as z:
            arrays = {k: z[k] for k in z.files}
        header = json.loads(arrays["header"].tobytes())
        header["n_components"] += 1
        arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
        np.savez(sidecar, **arrays)
    with pytest.raises(SemanticsFileError, match=r"m\.semantics\.npz.*--database"):
        SemanticModel.load(sidecar, model)
    r = CliRunner().invoke(app, ["generate", str(model_file), "--set", "stature=175cm", "--out",
                                 str(tmp_path / "a.obj")])
    assert r.exit_code == 2 and isinstance(r.exception, SystemExit), r.output
    assert "m.semantics.npz" in r.output and "--database" in r.output and "Traceback" not in r.output
    assert BodyModel.load(model_file).semantics is None  # nothing folded in


def test_damaged_semantics_in_the_model_file_refused(setup, app, tmp_path):
    root, _, model, sm = setup
    arrays = dict(np.load(root / "model.npz"))
    header = json.loads(arrays["header"].tobytes())
    arrays["semantics_meta"] = np.frombuffer(b"{broken", dtype=np.uint8)
    header["arrays"]["semantics_meta"]["shape"] = [7]
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ModelError, match=r"bad\.npz: the stored semantic regressors do not load.*refit"):
        BodyModel.load(tmp_path / "bad.npz")
    assert BodyModel.load(tmp_path / "bad.npz", semantics=False).semantics is None
    # the CLI's --refit replaces them
    r = CliRunner().invoke(app, ["generate", str(tmp_path / "bad.npz"), "--set", "stature=175cm", "--out",
                                 str(tmp_path / "a.obj")])
    assert r.exit_code == 2 and "--refit" in r.output and "Traceback" not in r.output, r.output
    r = CliRunner().invoke(app, ["generate", str(tmp_path / "bad.npz"), "--database", str(root / "db"), "--refit",
                                 "--set", "stature=175cm", "--out", str(tmp_path / "a.obj")])
    assert r.exit_code == 0, r.output
    assert BodyModel.load(tmp_path / "bad.npz").semantics is not None


def test_morph_accepts_the_models_own_folds(setup, tmp_path):
    """A decoded RRE body folds where the model's training scans fold; projecting it for a
    morph neither warns nor raises, whatever the encoder's flip policy."""
    _, db, _, _ = setup
    rre = BodyModel.fit(db, "rre", "rest", on_flipped="ignore")
    rre.encoder.on_flipped = "raise"
    sm = SemanticModel(rre).fit(db)
    x = rre.mean_vertices.copy()
    a, b, c = x[rre.faces[5000]]
    x[rre.faces[5000][0]] = a + 2.2 * ((b + c) / 2 - a)  # one vertex pushed across: folded triangles
    with pytest.raises(Exception, match="flipped triangle"):
        rre.project(x)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        result = sm.morph(x, {"stature": 0.02})
    assert abs(result.values["stature"] - result.targets["stature"]) <= tolerance("stature")


def test_cli_crowd_streams_random_bodies_with_a_bounded_line_up(setup, app, tmp_path, monkeypatch):
    """Nothing asked: the crowd is the model's random sample for the seed, decoded in chunks and
    written as made; the line-up holds only the first SHEET_MAX (here 2 of 3)."""
    import bodyspace.cli.semantics as cli_semantics
    monkeypatch.setattr(cli_semantics, "SHEET_MAX", 2)
    monkeypatch.setattr(cli_semantics, "SAMPLE_CHUNK", 2)
    root, _, _, _ = setup
    r = CliRunner().invoke(app, ["crowd", str(root / "model.npz"), "-n", "3", "--seed", "5",
                                 "--out", str(tmp_path / "c")])
    assert r.exit_code == 0, r.output
    rows = list(csv.DictReader(open(tmp_path / "c" / "crowd.csv")))
    assert [row["mesh"] for row in rows] == ["body_000.obj", "body_001.obj", "body_002.obj"]
    model = BodyModel.load(root / "model.npz")
    expected = model.sample(3, sigma_range=2.0, rng=5)
    for i in range(3):
        written, _ = load_mesh(tmp_path / "c" / f"body_{i:03d}.obj")
        assert np.abs(written - expected[i]).max() < 1e-5
    assert (tmp_path / "c" / "lineup.png").stat().st_size > 0
