"""BodyModel: fit, save/load (no pickle, versioned), sampling, projection, CLI build/sample, and
the shape-space reports on a tiny synthetic population."""

import json
import pickle
import zipfile

import numpy as np
import pytest
from typer.testing import CliRunner

from bodyspace.cli import app
from bodyspace.encoding import RelativeRotationEncoder, VertexEncoder
from bodyspace.errors import BodyspaceError, MeshError, ParameterError
from bodyspace.mesh.alignment import rigid_procrustes
from bodyspace.measure import load_measurement_set
from bodyspace.model import FORMAT_VERSION, BodyModel, ModelError
from bodyspace.report.shape_report import write_generalization_report, write_interpolation_report
from bodyspace.shape import ShapeSpace
from bodyspace.shape.solvers import pca_full, pca_randomized
from bodyspace.studies.generalization import generalization_study
from bodyspace.studies.interpolation import interpolation_study
from bodyspace.synth.population import build_population

runner = CliRunner()


@pytest.fixture(scope="module")
def db(template, tmp_path_factory):
    """4 subjects x (rest + 2 poses) = 12 scans."""
    return build_population(template, tmp_path_factory.mktemp("pop") / "db", 4, 2, rng=7)


@pytest.fixture(scope="module")
def model(db, template):
    return BodyModel.fit(db, "rre", "all", template=template, on_flipped="ignore")


def test_fit_attributes_and_reconstruction_of_a_training_scan(model, db):
    assert model.encoding == "rre" and model.selection == "all"
    assert model.n_components == db.n_scans - 1 and len(model.fitted_scans) == db.n_scans
    r = model.space.explained_variance_ratio_
    assert abs(r.sum() - 1) < 1e-6 and np.all(np.diff(model.space.explained_variance_) <= 1e-12)
    c = model.space.components_
    np.testing.assert_allclose(c @ c.T, np.eye(len(c)), atol=1e-5)  # float32-rounded components
    x = db.mesh(5)
    z = model.project(x)
    assert z.shape == (1, model.n_components)
    back = model.reconstruct(z)
    assert back.shape == (1, db.n_vertices, 3)
    target = rigid_procrustes(x, model.mean_vertices)[0]  # the documented placement
    assert np.abs(back[0] - target).max() < 1e-4  # metres; float32 components


def test_full_pca_matches_shape_space_and_randomized_finds_the_leading_components(model, db):
    codes = model.encode(np.asarray(db.vertices, dtype=float))
    ref = ShapeSpace(n_components=5).fit(codes)
    s, comps = pca_full(codes.copy(), codes.mean(axis=0))
    np.testing.assert_allclose(s[:5], ref.singular_values_, rtol=1e-8)
    np.testing.assert_allclose(np.abs(np.sum(comps[:5] * ref.components_, axis=1)), 1, atol=1e-8)
    s32, comps32 = pca_randomized(codes.astype(np.float32), codes.mean(axis=0), 3, rng=0)
    np.testing.assert_allclose(s32, ref.singular_values_[:3], rtol=1e-3)
    np.testing.assert_allclose(np.abs(np.sum(comps32 * ref.components_[:3], axis=1)), 1, atol=1e-3)


def test_save_load_round_trip_is_bit_exact(model, db, tmp_path):
    path = model.save(tmp_path / "m.npz")
    assert not list(tmp_path.glob("*.part")), "written atomically"
    back = BodyModel.load(path)
    for name, a in model._arrays().items():
        b = back._arrays()[name]
        assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b), name
    assert back.encoding == "rre" and back.selection == "all" and back.template_id == model.template_id
    assert back.encoder.on_flipped == "ignore"
    x = np.asarray(db.vertices[:3], dtype=float)
    np.testing.assert_array_equal(back.encode(x), model.encode(x))
    np.testing.assert_array_equal(back.project(x, method="code"), model.project(x, method="code"))
    np.testing.assert_array_equal(back.project(x[:1]), model.project(x[:1]))  # the vertex fit: one mesh
    z = model.sample_coefficients(2, n_components=3, rng=1)
    np.testing.assert_allclose(back.reconstruct(z), model.reconstruct(z), atol=1e-9)


def test_model_files_of_the_iterative_decoder_still_load(model, tmp_path):
    """Files written while the default decoder was block CG name it "pcg" and may carry its step
    settings; they load, with the exact decoder."""
    path = model.save(tmp_path / "old.npz")
    with np.load(path, allow_pickle=False) as f:
        arrays = dict(f)
    header = json.loads(arrays["header"].tobytes().decode("utf-8"))
    header["encoder_params"] = {"rotation_solver": "pcg", "tol": 1e-5, "max_iter": 20, "on_flipped": "ignore"}
    arrays["header"] = np.frombuffer(json.dumps(header).encode("utf-8"), dtype=np.uint8)
    np.savez(tmp_path / "old.npz", **arrays)
    back = BodyModel.load(tmp_path / "old.npz")
    assert back.encoder.rotation_solver == "exact"
    z = model.sample_coefficients(2, n_components=3, rng=2)
    np.testing.assert_allclose(back.reconstruct(z), model.reconstruct(z), atol=1e-9)


def _save_v1(model, path):
    """A frozen copy of the writer of format version 1 (bodyspace up to commit 90b48a0): its array
    names and header, so files of that version stay loadable whatever the current writer does."""
    sp, enc = model.space, model.encoder
    arrays = {
        "template_vertices": model.template_vertices.astype(np.float64),
        "faces": model.faces.astype(np.int64),
        "encoder_mean_vertices": np.asarray(enc.mean_vertices_, dtype=np.float64),
        "pca_mean": np.asarray(sp.mean_, dtype=np.float64),
        "pca_components": np.asarray(sp.components_, dtype=np.float32),
        "pca_explained_variance": np.asarray(sp.explained_variance_, dtype=np.float64),
        "pca_explained_variance_ratio": np.asarray(sp.explained_variance_ratio_, dtype=np.float64),
        "pca_singular_values": np.asarray(sp.singular_values_, dtype=np.float64),
        "fitted_scans": model.fitted_scans.astype(np.int64),
    }
    if model.encoding == "rre":
        arrays["rre_mean_rotvecs"] = np.asarray(enc.mean_rotvecs_, dtype=np.float64)
        arrays["rre_mean_stretch"] = np.asarray(enc.mean_stretch_, dtype=np.float64)
    header = {
        "format": "bodyspace.BodyModel", "format_version": 1, "encoding": model.encoding,
        "encoder_params": model.encoder_params, "template_id": model.template_id,
        "selection": model.selection, "n_samples": int(sp.n_samples_), "n_components": model.n_components,
        "n_vertices": int(len(model.template_vertices)), "n_faces": int(len(model.faces)),
        "n_features": int(sp.n_features_in_),
        "units": {"length": "m", "rre_code": "rotation vectors (rad) and stretch (1) per triangle", "vertex_code": "m"},
        "provenance": {"generator": "bodyspace.model.BodyModel.fit", "pca_solver": "full"}, "mapping": None,
        "arrays": {name: {"shape": list(a.shape), "dtype": a.dtype.str} for name, a in arrays.items()},
    }
    arrays["header"] = np.frombuffer(json.dumps(header).encode("utf-8"), dtype=np.uint8)
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)


def test_model_files_of_format_version_1_still_load(model, db, template, tmp_path):
    vertex = BodyModel.fit(db, "vertex", "rest", n_components=2, template=template)
    for m in (model, vertex):
        _save_v1(m, tmp_path / "v1.npz")
        back = BodyModel.load(tmp_path / "v1.npz")
        assert back.encoding == m.encoding and back.space.n_samples_ == m.space.n_samples_
        for name, a in m._arrays().items():
            assert np.array_equal(a, back._arrays()[name]), name
        x = np.asarray(db.vertices[:2], dtype=float)
        np.testing.assert_array_equal(back.project(x), m.project(x))
        z = m.sample_coefficients(2, rng=3)
        np.testing.assert_array_equal(back.reconstruct(z), m.reconstruct(z))
        # a version 1 file of the template's topology gets the shipped measurement set, and
        # re-saved is a file of the current version with the same content and that set stored
        assert back.measurement_set.names == load_measurement_set().names
        again = BodyModel.load(back.save(tmp_path / "v3.npz"))
        with np.load(tmp_path / "v3.npz") as f:
            assert json.loads(f["header"].tobytes())["format_version"] == FORMAT_VERSION == 3
            assert "measurement_set" in f.files
        np.testing.assert_array_equal(again.reconstruct(z), m.reconstruct(z))
        assert again.measurement_set.measurements == load_measurement_set().measurements


def test_vertex_model_rest_selection_and_sampling(db, template, tmp_path):
    m = BodyModel.fit(db, "vertex", "rest", n_components=2, template=template)
    assert m.selection == "rest" and len(m.fitted_scans) == 4 and m.n_components == 2
    assert set(db.scans["pose"][m.fitted_scans]) == {"rest"}
    bodies = m.sample(3, n_components=2, sigma_range=(-1.0, 1.0), rng=0)
    assert bodies.shape == (3, db.n_vertices, 3) and np.isfinite(bodies).all()
    back = BodyModel.load(m.save(tmp_path / "v.npz"))
    np.testing.assert_array_equal(back.sample(3, 2, (-1.0, 1.0), rng=0), bodies)
    assert isinstance(back.encoder, VertexEncoder)


def _rewrite(src, dst, change):
    with np.load(src, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    change(arrays)
    with open(dst, "wb") as fh:
        np.savez(fh, **arrays)


def test_load_refuses_garbage_pickles_versions_and_missing_fields(model, tmp_path):
    good = model.save(tmp_path / "good.npz")
    (tmp_path / "garbage.npz").write_bytes(b"not a model at all")
    with pytest.raises(ModelError, match="garbage.npz.*not a BodyModel file"):
        BodyModel.load(tmp_path / "garbage.npz")
    (tmp_path / "p.npz").write_bytes(pickle.dumps({"a": 1}))
    with pytest.raises(ModelError, match="never pickles"):
        BodyModel.load(tmp_path / "p.npz")
    # an .npz whose field holds a pickled object array
    _rewrite(good, tmp_path / "obj.npz", lambda a: a.__setitem__("pca_mean", np.array([object()], dtype=object)))
    with pytest.raises(ModelError, match="obj.npz: field 'pca_mean'.*pickle"):
        BodyModel.load(tmp_path / "obj.npz")

    def bump(a):
        h = json.loads(a["header"].tobytes())
        h["format_version"] = 99
        a["header"] = np.frombuffer(json.dumps(h).encode(), dtype=np.uint8)
    _rewrite(good, tmp_path / "v99.npz", bump)
    with pytest.raises(ModelError, match="v99.npz: format_version 99.*reads versions 1, 2, 3.*upgrade"):
        BodyModel.load(tmp_path / "v99.npz")
    _rewrite(good, tmp_path / "missing.npz", lambda a: a.pop("encoder_mean_stretch"))
    with pytest.raises(ModelError, match="missing.npz: field 'encoder_mean_stretch' is missing"):
        BodyModel.load(tmp_path / "missing.npz")

    def header_field(name, value):
        def change(a):
            h = json.loads(a["header"].tobytes())
            h[name] = value
            a["header"] = np.frombuffer(json.dumps(h).encode(), dtype=np.uint8)
        return change
    for name, value, message in [("arrays", "all of them", "header field 'arrays' is str"),
                                 ("arrays", {"faces": 3}, "header field 'arrays' is malformed"),
                                 ("n_samples", "many", "header field 'n_samples' is 'many', expected a count"),
                                 ("encoder_params", [1], "header field 'encoder_params'"),
                                 ("encoder_params", {"colour": "red"}, "do not make an encoder"),
                                 ("template_id", 7, "header field 'template_id' is 7")]:
        _rewrite(good, tmp_path / "h.npz", header_field(name, value))
        with pytest.raises(ModelError, match=message):
            BodyModel.load(tmp_path / "h.npz")
    with zipfile.ZipFile(tmp_path / "nohdr.npz", "w") as zf:
        zf.writestr("x.npy", b"")
    with pytest.raises(ModelError, match="field 'header' is missing|cannot be read"):
        BodyModel.load(tmp_path / "nohdr.npz")
    with pytest.raises(ModelError, match="no such file"):
        BodyModel.load(tmp_path / "nope.npz")
    assert issubclass(ModelError, BodyspaceError)


def test_cli_build_and_sample(db, tmp_path):
    out = tmp_path / "m.npz"
    db_path = str(db.meta.get("path", "")) or None
    folder = tmp_path / "db"
    db.save(folder)
    result = runner.invoke(app, ["build", str(folder), "--out", str(out), "--selection", "rest",
                                 "--encoding", "vertex"])
    assert result.exit_code == 0, result.output
    assert BodyModel.load(out).n_components == 3
    again = runner.invoke(app, ["build", str(folder), "--out", str(out)])
    assert again.exit_code == 2 and "--force" in again.output
    result = runner.invoke(app, ["sample", str(out), "-n", "2", "--out", str(tmp_path / "s"), "--format", "ply",
                                 "--components", "2"])
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in (tmp_path / "s").iterdir() if p.name != ".bodyspace") == ["body_000.ply", "body_001.ply",
                                                                                     "samples.png"]
    bad = runner.invoke(app, ["sample", str(folder / "faces.npy"), "--out", str(tmp_path / "t")])
    assert bad.exit_code == 2 and "not a BodyModel file" in bad.output
    del db_path
    banana = runner.invoke(app, ["build", str(folder), "--out", str(tmp_path / "b.npz"), "--on-flipped", "banana"])
    assert banana.exit_code == 2 and "Traceback" not in banana.output
    assert "--on-flipped 'banana': expected one of accept, warn, raise, ignore" in banana.output
    assert not (tmp_path / "b.npz").exists()


def test_flipped_scans_are_accepted_and_counted_once_by_default(db, template, tmp_path):
    """The LBS-posed scans fold triangles: the default encodes them and counts the scans (not the
    warnings); "raise" refuses; the CLI prints the count."""
    folder = tmp_path / "db"
    db.save(folder)
    result = runner.invoke(app, ["build", str(folder), "--out", str(tmp_path / "m.npz"), "--selection", "all",
                                 "--components", "3"])
    assert result.exit_code == 0, result.output
    model = BodyModel.load(tmp_path / "m.npz")
    probe = RelativeRotationEncoder(template.vertices, template.faces).fit(template.vertices[None])
    probe.encode(np.asarray(db.vertices, dtype=float))
    expected = int(np.count_nonzero(probe.last_flipped_))
    assert 0 < expected < db.n_scans
    assert model.provenance["flipped_scans"] == expected
    assert model.provenance["flipped_triangles_max"] == int(probe.last_flipped_.max())
    assert f"{expected} of {db.n_scans} scan(s) have flipped (folded) triangles" in " ".join(result.output.split())
    with pytest.raises(MeshError, match="flipped triangle"):
        BodyModel.fit(db, "rre", "all", n_components=3, template=template, on_flipped="raise")
    with pytest.raises(ParameterError, match="on_flipped='banana'"):
        BodyModel.fit(db, "rre", "all", template=template, on_flipped="banana")


def test_shape_reports_on_a_tiny_database(db, model, template, tmp_path):
    vertex = VertexEncoder(template.vertices, template.faces).fit(np.asarray(db.vertices, dtype=float))
    res = interpolation_study(db, {"rre": model.encoder, "vertex": vertex}, n_subjects=1)
    assert res["pairs"] == 3 and len(res["rows"]) == 3
    s = res["summary"]
    assert all(np.isfinite(v) for e in s.values() for v in e.values())
    assert s["rre"]["edge_change_mean"] < s["vertex"]["edge_change_mean"]
    files = write_interpolation_report(res, db.faces, tmp_path)
    assert all((tmp_path / f).stat().st_size > 0 for f in files.values())
    gen = generalization_study(db, {"rre": model.encoder, "vertex": vertex}, selection="all", n_folds=2,
                               components=(1,), max_iter=3, max_jacobians=1, bases=("code", "vertex"))
    assert gen["components"] == [1, 12 - 3 - 1]
    # RRE with both projections in both component orders, vertex PCA once (its two projections
    # and orders are one).
    assert set(gen["error_m"]) == {"rre code", "rre vertex", "rre vertex-basis code", "rre vertex-basis vertex",
                                   "vertex"}
    assert gen["models"]["rre vertex"] == {"encoder": "rre", "projection": "vertex", "basis": "code"}
    assert gen["models"]["rre vertex-basis vertex"] == {"encoder": "rre", "projection": "vertex", "basis": "vertex"}
    for name in gen["error_m"]:
        e = np.asarray(gen["error_m"][name])
        assert e.shape == (len(gen["components"]),) and np.isfinite(e).all() and (e > 0).all()
        # Aligning each region rigidly first leaves only the local shape error: never much larger.
        local = np.asarray(gen["local_error_m"][name])
        assert local.shape == e.shape and np.isfinite(local).all() and (local <= 1.05 * e + 1e-9).all()
        assert (np.asarray(gen["max_error_m"][name]) >= e).all() and len(gen["fit_s"][name]) == len(e)
    # The vertex fit starts from the code projection and only takes steps that lower the error.
    for basis in ("", " vertex-basis"):
        assert (np.asarray(gen["error_m"][f"rre{basis} vertex"])
                <= 1.02 * np.asarray(gen["error_m"][f"rre{basis} code"])).all()
    assert gen["local_regions"] == 12
    # The demo's posed study leaves out the costly count of all components.
    short = generalization_study(db, {"vertex": vertex}, selection="all", n_folds=1, components=(1, 2),
                                 with_all_components=False)
    assert short["components"] == [1, 2]
    with pytest.raises(ParameterError, match="none between 1 and"):
        generalization_study(db, {"vertex": vertex}, selection="all", n_folds=1, components=(500,),
                             with_all_components=False)
    files = write_generalization_report([gen, gen], tmp_path)
    written = json.loads((tmp_path / files["json"]).read_text())["studies"][0]
    assert written["units"]["error"] == "mm"
    # The study is in metres, the report in mm (a body's error is millimetres, never metres).
    assert np.allclose(written["error_mm"]["vertex"], 1000.0 * np.asarray(gen["error_m"]["vertex"]))
    assert (np.asarray(gen["error_m"]["rre code"]) < 0.2).all()
    table = (tmp_path / files["table"]).read_text()
    assert "rre PCA, vertex fit" in table and "rre PCA, code projection" in table and "vertex PCA" in table
