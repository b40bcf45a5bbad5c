"""Training data, measurement Jacobians, exact refinement and the three-method evaluation."""

import dataclasses

import numpy as np
import pytest

from bodyspace.errors import ParameterError
from bodyspace.mapping import LinearLeafForest, LinearMapping
from bodyspace.mapping.gradients import (
    RUPPRECHT_SIX,
    LinearBodyMeasures,
    distance_grad,
    loop_length_grad,
    path_length_grad,
    subset,
    unit_vector_grad,
)
from bodyspace.mapping.refine import refine
from bodyspace.mapping.training import make_training_set
from bodyspace.measure import load_measurement_set, measure


@pytest.fixture(scope="module")
def db(template, tmp_path_factory):
    from bodyspace.synth.population import build_population
    return build_population(template, tmp_path_factory.mktemp("mapping") / "db", 24, 0, rng=0)


@pytest.fixture(scope="module")
def model(db):
    from bodyspace.model import BodyModel
    return BodyModel.fit(db, encoding="vertex", selection="rest")


@pytest.fixture(scope="module")
def mset():
    return load_measurement_set()


@pytest.fixture(scope="module")
def fitted(model):
    train = make_training_set(model, 1500, rng=0)
    held = make_training_set(model, 100, rng=1)
    X, Y = train.measurements, train.coefficients[:, :train.k]
    return (train, held, LinearMapping().fit(X, Y),
            LinearLeafForest(n_trees=20, rng=0, n_jobs=1).fit(X, Y))


def _fd(f, x, h=1e-6):
    """Central differences of f: (..., D) -> (...) over the last axis of x (..., D)."""
    g = np.zeros_like(x)
    for idx in np.ndindex(*x.shape[1:]):
        e = np.zeros_like(x)
        e[(slice(None),) + idx] = h
        g[(slice(None),) + idx] = (f(x + e) - f(x - e)) / (2 * h)
    return g


def test_vertex_level_jacobians_match_finite_differences():
    rng = np.random.default_rng(0)
    ring = rng.normal(size=(3, 9, 3))
    ax = np.array([0.2, 1.0, -0.1])
    ax /= np.linalg.norm(ax)
    _, g = loop_length_grad(ring, ax)
    np.testing.assert_allclose(g, _fd(lambda r: loop_length_grad(r, ax)[0], ring), atol=1e-7)
    pts = rng.normal(size=(3, 4, 3))
    np.testing.assert_allclose(path_length_grad(pts)[1], _fd(lambda p: path_length_grad(p)[0], pts), atol=1e-7)
    a, b, p, q = rng.normal(size=(4, 3, 3))

    def dist(a, b, p, q):
        d = q - p
        return distance_grad(a, b, d / np.linalg.norm(d, axis=-1, keepdims=True))[0]

    d = q - p
    _, ga, gb, gax = distance_grad(a, b, d / np.linalg.norm(d, axis=-1, keepdims=True))
    gp, gq = unit_vector_grad(p, q, gax)
    np.testing.assert_allclose(ga, _fd(lambda x: dist(x, b, p, q), a), atol=1e-7)
    np.testing.assert_allclose(gb, _fd(lambda x: dist(a, x, p, q), b), atol=1e-7)
    np.testing.assert_allclose(gp, _fd(lambda x: dist(a, b, x, q), p), atol=1e-7)
    np.testing.assert_allclose(gq, _fd(lambda x: dist(a, b, p, x), q), atol=1e-7)
    _, ga, gb, _ = distance_grad(a, b, None)
    np.testing.assert_allclose(gb, _fd(lambda x: distance_grad(a, x, None)[0], b), atol=1e-7)


def test_coefficient_jacobians_match_finite_differences_and_evaluate(model, mset):
    tilted = {"name": "tilted", "method": "distance", "from": "crotch", "to": "head_top", "unit": "m",
              "axis": ["crotch", ["neck_front", "neck_back"]], "requires": []}
    ms = dataclasses.replace(mset, measurements=mset.measurements + (tilted,))
    names = RUPPRECHT_SIX + ("arm_length_l", "shoulder_width", "tilted")
    lb = LinearBodyMeasures.from_model(model, ms, names)
    sd = np.sqrt(model.space.explained_variance_)
    z = np.random.default_rng(3).uniform(-2, 2, (4, len(sd))) * sd
    vals, J = lb(z, jacobian=True)
    h = 1e-6 * sd
    fd = np.stack([(lb(z + h[k] * np.eye(len(sd))[k]) - lb(z - h[k] * np.eye(len(sd))[k])) / (2 * h[k])
                   for k in range(len(sd))], axis=-1)
    np.testing.assert_allclose(J, fd, atol=1e-6 * np.abs(J).max())
    ref = measure(subset(ms, names), model.reconstruct(z), model.faces)
    want = np.stack([ref[n] for n in names], axis=1)
    ok = np.isfinite(want)          # "not upright" bodies are NaN in evaluate, measured here as in the paper
    np.testing.assert_allclose(vals[ok], want[ok], atol=1e-10)


def test_slices_are_refused_with_a_reason_and_the_encoder_linearizes_itself(model, mset):
    with pytest.raises(ParameterError, match="no analytic Jacobian"):
        LinearBodyMeasures.from_model(model, mset, ("waist_girth",))
    # mapping asks the encoder, never its kind: the vertex encoder's linearization is exact
    assert model.encoder.is_linear
    lin = model.encoder.linearize(model.space, 4)
    assert lin.method_ == "exact" and lin.k == 4
    z = np.random.default_rng(8).uniform(-2, 2, (3, 4)) * np.sqrt(model.space.explained_variance_[:4])
    np.testing.assert_allclose(lin.predict(z), model.reconstruct(z), atol=1e-12)


def test_measure_bodies_matches_the_linear_path_and_chains_the_basis(model):
    lb = LinearBodyMeasures.from_model(model)
    sd = np.sqrt(model.space.explained_variance_)
    z = np.random.default_rng(4).uniform(-2, 2, (3, len(sd))) * sd
    vals, J = lb(z, jacobian=True)
    vals2, J2 = lb.measure_bodies(model.reconstruct(z), jacobian=True)
    np.testing.assert_allclose(vals2, vals, atol=1e-12)
    np.testing.assert_allclose(J2, J, atol=1e-9 * np.abs(J).max())


def test_decoder_linearization_fits_a_linear_decoder_exactly_and_round_trips(model):
    from bodyspace.encoding.linearize import DecoderLinearization
    sd = np.sqrt(model.space.explained_variance_[:5])
    z = np.random.default_rng(2).uniform(-3, 3, (12, 5)) * sd
    v = model.reconstruct(z)
    lin = DecoderLinearization(5).partial_fit(z[:4], v[:4]).partial_fit(z[4:], v[4:])
    V = len(model.mean_vertices)
    np.testing.assert_allclose(lin.basis_, model.space.components_[:5].reshape(5, V, 3), atol=1e-8)
    assert lin.residual_rms_ < 1e-4 and lin.n_samples_ == 12      # from sums: ~1e-5 m rounding
    np.testing.assert_allclose(lin.predict(z), v, atol=1e-9)
    back = DecoderLinearization.from_arrays(lin.to_arrays())
    np.testing.assert_array_equal(back.basis_, lin.basis_)
    with pytest.raises(ParameterError, match="not fitted"):
        DecoderLinearization(5).fit(z[:3], v[:3]).predict(z)


def test_training_set_is_deterministic_and_in_the_box(model):
    a = make_training_set(model, 200, rng=5)
    b = make_training_set(model, 200, rng=5)
    c = make_training_set(model, 200, rng=6)
    np.testing.assert_array_equal(a.measurements, b.measurements)
    np.testing.assert_array_equal(a.coefficients, b.coefficients)
    assert not np.array_equal(a.coefficients, c.coefficients)
    sd = np.sqrt(model.space.explained_variance_[:a.k])
    assert np.all(np.abs(a.coefficients[:, :a.k]) <= 3 * sd)
    assert a.names == RUPPRECHT_SIX and a.units == ("cm",) * 6
    assert 120 < a.column("height").mean() < 220
    # any other measurement of the set, e.g. a slice, goes through evaluate
    d = make_training_set(model, 3, rng=5, names=("height", "waist_girth"))
    np.testing.assert_allclose(d.measurements[:, 0], a.measurements[:3, 0])
    assert np.all((d.measurements[:, 1] > 40) & (d.measurements[:, 1] < 200))


def test_forest_beats_linear_on_every_parameter(model, fitted):
    train, held, lin, forest = fitted
    lb = LinearBodyMeasures.from_model(model)
    err = {name: lb(est.predict(held.measurements)) * 100 - held.measurements
           for name, est in (("linear", lin), ("forest", forest))}
    assert np.all(err["forest"].var(axis=0) < err["linear"].var(axis=0))


def test_refinement_meets_feasible_requests_within_1mm(model, fitted):
    _, held, _, forest = fitted
    res = refine(model, forest.predict(held.measurements), held.measurements)
    err = np.abs(res.measured - held.measurements).max(axis=1)
    assert np.mean(err <= 0.1) >= 0.99
    assert sum(bool(m) for m in res.misses) <= 1 and res.decodes == 0          # vertex path: nothing decoded
    # the reported measurements are the body's
    lb = LinearBodyMeasures.from_model(model)
    np.testing.assert_allclose(lb(res.coefficients) * 100, res.measured, atol=1e-9)
    sd = np.sqrt(model.space.explained_variance_[:len(res.coefficients[0])])
    assert np.all(np.abs(res.coefficients / sd) <= 3 + 1e-9)


def test_infeasible_request_gets_closest_plausible_body_and_report(model, fitted):
    _, held, _, forest = fitted
    req = held.measurements[:2].copy()
    req[:, 0] += 60.0                      # 60 cm taller, same legs: no body in the box
    res = refine(model, forest.predict(req), req)
    assert not res.met.any()
    miss = res.misses[0]
    assert "height" in miss or "leg_length" in miss
    for v in miss.values():
        assert abs(v["measured"] - v["requested"] - v["difference"]) < 1e-9 and abs(v["difference"]) > 0.1
    sd = np.sqrt(model.space.explained_variance_[:res.coefficients.shape[1]])
    assert np.all(np.abs(res.coefficients / sd) <= 3 + 1e-9)
    # closer than the start
    lb = LinearBodyMeasures.from_model(model)
    start = np.abs(lb(forest.predict(req)) * 100 - req).sum()
    assert np.abs(res.measured - req).sum() < start
    one = refine(model, forest.predict(req[0]), req[0])
    assert one.coefficients.ndim == 1 and one.measured.shape == (6,)


def test_evaluation_report_files(model, tmp_path):
    from bodyspace.report.mapping_report import write_mapping_report
    from bodyspace.studies.mapping import METHODS, evaluate_mapping
    ev, fitted = evaluate_mapping(model, samples=600, held_out=30, rng=0, n_trees=4, n_jobs=1)
    assert tuple(ev.errors) == METHODS and ev.errors["forest"].shape == (30, 6)
    assert ev.within("forest + refinement") >= 0.96
    assert ev.settings["exact_by_construction"] == []      # Rupprecht's six: none is affine in the coefficients
    assert min(ev.settings["affine_residual_cm"].values()) > 0.01
    files = write_mapping_report(model, ev, tmp_path / "out")
    for f in files.values():
        assert f.exists() and f.stat().st_size > 0
    text = files["tables"].read_text()
    assert "forest + refinement variance" in text and "shoulder_size sweep" in text
    assert len(ev.sweep["measured"]) == 5


# ---------------------------------------------------------------------------------- RRE models
# Every RRE body is decoded (~0.05-0.4 s each): a small model (8 components, 12 scans), 32
# training bodies and 4 held-out requests keep these tests to a few dozen decodes.
RRE_K = 8


@pytest.fixture(scope="module")
def rre_model(db, template):
    from bodyspace.model import BodyModel
    return BodyModel.fit(db, "rre", np.arange(12), n_components=RRE_K, template=template, on_flipped="ignore")


@pytest.fixture(scope="module")
def rre_evaluation(rre_model):
    from bodyspace.studies.mapping import evaluate_mapping
    return evaluate_mapping(rre_model, samples=32, held_out=4, rng=0, k=RRE_K, n_trees=2, n_jobs=1, sweep=False)


def test_rre_encoder_linearizes_by_forward_differences_at_the_mean(rre_model):
    enc = rre_model.encoder
    assert not enc.is_linear
    lin = enc.linearize(rre_model.space, 3)
    assert lin.method_ == "finite_differences" and lin.k == 3
    np.testing.assert_allclose(lin.base_, rre_model.reconstruct(np.zeros((1, rre_model.n_components)))[0],
                               atol=1e-12)
    h = 1e-3 * np.sqrt(rre_model.space.explained_variance_[0])
    z = np.zeros((1, rre_model.n_components))
    z[0, 0] = h
    step = (rre_model.reconstruct(z)[0] - lin.base_) / h
    assert np.abs(step - lin.basis_[0]).max() < 0.05 * np.abs(lin.basis_[0]).max()


def test_rre_refinement_meets_held_out_requests_within_1mm(rre_evaluation):
    ev, fitted = rre_evaluation
    assert ev.settings["encoding"] == "rre" and ev.errors["forest"].shape == (4, 6)
    lin = fitted["linearization"]
    assert lin is not None and lin.k == RRE_K and lin.n_samples_ == 32
    # 32 training bodies make a rough forest and linearization: 3 of the 4 requests are met (all
    # six within 1 mm); the 4th, started cm off near a box corner, ends in a local minimum
    # against the box and is reported as missed (with 400 training bodies and 23 components
    # every request was met, see docs/mapping.md)
    within = ev.within("forest + refinement")
    assert within >= 0.75 and ev.within("forest") < within
    assert ev.settings["refine_misses"] == round((1 - within) * 4)
    assert ev.settings["refine_iterations_max"] <= 40


def test_rre_infeasible_request_gets_closest_plausible_body_and_report(rre_model, rre_evaluation):
    ev, fitted = rre_evaluation
    req = ev.requests[:1].copy()
    req[:, 0] += 60.0                      # 60 cm taller, same legs: no body in the box
    z0 = fitted["forest"].predict(req)
    res = refine(rre_model, z0, req, k=RRE_K, linearization=fitted["linearization"], max_iter=6)
    assert not res.met.any() and res.iterations[0] <= 6
    miss = res.misses[0]
    assert "height" in miss or "leg_length" in miss
    for v in miss.values():
        assert abs(v["measured"] - v["requested"] - v["difference"]) < 1e-9 and abs(v["difference"]) > 0.1
    sd = np.sqrt(rre_model.space.explained_variance_[:RRE_K])
    assert np.all(np.abs(res.coefficients[:, :RRE_K] / sd) <= 3 + 1e-9)
    # the reported measurements are those of the decoded body, and closer than the start's
    ref = measure(subset(load_measurement_set(), RUPPRECHT_SIX), rre_model.reconstruct(res.coefficients),
                  rre_model.faces)
    want = np.array([ref[n][0] for n in RUPPRECHT_SIX]) * 100
    ok = np.isfinite(want)             # a body this tall may lean past "upright": NaN in evaluate
    assert ok.sum() >= 4
    np.testing.assert_allclose(want[ok], res.measured[0][ok], atol=1e-6)
    lb = LinearBodyMeasures.from_model(rre_model, k=RRE_K, linearization=fitted["linearization"])
    start = lb.measure_bodies(rre_model.reconstruct(z0)) * 100
    assert np.abs(res.measured - req).sum() < np.abs(start - req).sum()


def test_mapping_is_stored_in_the_model_file_and_makes_bodies(tmp_path, model):
    """fit_mapping -> save -> load keeps the forest bit-exact; `mapping shape` makes a body that
    measures the six requested values within 1 mm; a model without a mapping is refused."""
    import json

    from typer.testing import CliRunner

    from bodyspace.cli import app
    from bodyspace.mapping.gradients import LinearBodyMeasures
    from bodyspace.model import BodyModel

    model = BodyModel.load(model.save(tmp_path / "copy.npz"))  # the fixture stays as it was
    model.fit_mapping(samples=400, k=8, n_trees=5)
    path = model.save(tmp_path / "m.npz")
    header = json.loads(np.load(path)["header"].tobytes())
    assert header["mapping"]["k"] == 8 and len(header["mapping"]["names"]) == 6
    back = BodyModel.load(path)
    X = np.asarray(model.mapping.forest.predict(np.zeros((1, 6)) + 100.0))
    assert np.array_equal(back.mapping.forest.predict(np.zeros((1, 6)) + 100.0), X)
    # a request measured on a body of the model: feasible by construction
    z = model.sample_coefficients(1, n_components=8, sigma_range=1.0, rng=3)
    goal = LinearBodyMeasures.from_model(model, names=back.mapping.names, k=8)(z[:, :8])[0] * 100.0
    args = ["mapping", "shape", str(path), "--out", str(tmp_path / "b.obj")]
    for name, v in zip(back.mapping.names, goal):
        args += ["--set", f"{name}={v:.4f}cm"]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    from bodyspace.mesh.io import load_mesh
    v, _ = load_mesh(tmp_path / "b.obj")
    got = LinearBodyMeasures.from_model(model, names=back.mapping.names, k=8).measure_bodies(v[None])[0] * 100.0
    assert np.abs(got - goal).max() < 0.1, (got, goal)
    # stature is the quantity of the input height: asking it fixes that input, not a draw
    names = list(back.mapping.names)
    x = back.mapping.inputs(back, {"stature": 175.0, "waist_size": 80.0}, rng=0)
    assert x[0, names.index("height")] == 175.0 and x[0, names.index("waist_size")] == 80.0
    r = CliRunner().invoke(app, ["mapping", "shape", str(path), "--out", str(tmp_path / "s.obj"),
                                 "--set", "stature=175cm", "--set", "waist_size=80cm"])
    assert r.exit_code == 0, r.output
    drawn = next(line for line in r.output.splitlines() if "drawn from the population" in line)
    assert "height" not in drawn and "breast_size" in drawn, drawn
    bare = BodyModel.load(path)
    bare.mapping = None
    bare.save(tmp_path / "bare.npz")
    r = CliRunner().invoke(app, ["mapping", "shape", str(tmp_path / "bare.npz"), "--out", str(tmp_path / "c.obj"),
                                 "--set", "height=170cm"])
    assert r.exit_code == 2 and "mapping fit" in r.output


# ------------------------------------------------------- inputs that no mapping can get wrong
def _with_set(model, mset):
    """A shallow copy of ``model`` that measures with ``mset`` (the fixture stays as it was)."""
    import copy
    other = copy.copy(model)
    other.measurement_set = mset
    return other


def test_an_input_affine_in_the_coefficients_is_flagged_not_shown_as_a_perfect_error(model, mset):
    # Without the shoulder_size loop the inputs take shoulder_width (biacromial, a straight
    # distance between mirrored landmarks) as on another topology: affine in a vertex model's
    # coefficients, so the linear mapping and every forest leaf return it exactly. It was shown
    # as "+0.0000 / 0.0000" for both, read as a perfect forest (the foreign-topology audit).
    from bodyspace.report.mapping_report import format_error, mapping_tables_markdown
    from bodyspace.studies.mapping import evaluate_mapping, exact_by_construction_note
    no_loop = dataclasses.replace(mset, measurements=tuple(m for m in mset.measurements
                                                            if m["name"] != "shoulder_size"))
    ev, _ = evaluate_mapping(_with_set(model, no_loop), samples=300, held_out=12, rng=0, n_trees=3, n_jobs=1,
                             sweep=False)
    assert ev.names[-1] == "shoulder_width"
    assert ev.settings["exact_by_construction"] == ["shoulder_width"]
    res = ev.settings["affine_residual_cm"]
    assert res["shoulder_width"] < 1e-6 and min(r for n, r in res.items() if n != "shoulder_width") > 0.01
    for m in ("linear", "forest"):                   # the number itself is right: 0 up to rounding
        assert np.abs(ev.errors[m][:, -1]).max() < 1e-3
    text = mapping_tables_markdown(ev)
    assert "| shoulder_width * |" in text and "exact by construction (*): shoulder_width" in text
    assert "tests neither method" in exact_by_construction_note(ev)
    row = next(line for line in text.splitlines() if line.startswith("| shoulder_width"))
    assert "0.0000" not in row                       # a non-zero error is never printed as 0
    assert format_error(6.2e-6) == "+6e-06" and format_error(0.0) == "+0.0000" and format_error(-0.0297) == "-0.0297"


def test_a_constant_or_repeated_input_is_refused(model, mset):
    # both shoulder landmarks on one vertex: shoulder_width is 0 on every body, and every
    # mapping would "meet" it with an error of exactly 0
    lm = dict(mset.landmarks)
    lm["shoulder_r"] = lm["shoulder_l"]
    same = dataclasses.replace(mset, landmarks=lm)
    with pytest.raises(ParameterError, match=r"'shoulder_width'.*0\.0000 cm on every one of the 40 bodies.*"
                                             r"shoulder_l, shoulder_r.*--landmarks"):
        make_training_set(_with_set(model, same), 40, rng=0, names=("height", "waist_size", "shoulder_width"))
    # leg_length and crotch_height are one definition under two names
    with pytest.raises(ParameterError, match="'leg_length'.*affine function of the other inputs.*asked twice"):
        make_training_set(model, 40, rng=0, names=("height", "waist_size", "leg_length", "crotch_height"))
