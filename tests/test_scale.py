"""Scale on one machine (issue 16): a database measured into one CSV row per scan."""

import csv

import numpy as np
import pytest
from typer.testing import CliRunner

from bodyspace.cli import app
from bodyspace.measure import evaluate, load_measurement_set
from bodyspace.synth.population import build_population

runner = CliRunner()


@pytest.fixture(scope="module")
def small_db(template, tmp_path_factory):
    return build_population(template, tmp_path_factory.mktemp("scale") / "db", 6, 2, rng=11, chunk=4)


def _rows(path):
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def test_measure_database_one_row_per_scan(small_db, tmp_path):
    """Every scan measured, in order, with its subject and pose; rest scans measure as the mesh
    does, posed scans are unposed first and measure close to their subject's rest scan."""
    out = tmp_path / "m.csv"
    result = runner.invoke(app, ["measure", str(small_db.folder), "--csv", str(out)])
    assert result.exit_code == 0, result.output
    assert "18 scans x" in result.output and "unposed first" in result.output
    rows = _rows(out)
    assert [r["scan"] for r in rows] == [str(i) for i in range(18)]
    assert [r["subject"] for r in rows] == small_db.scans["subject"].tolist()
    assert [r["pose"] for r in rows] == small_db.scans["pose"].tolist()
    mset = load_measurement_set()
    rest = np.flatnonzero(small_db.scans["pose"] == "rest")
    row = small_db.scan_subject_index()
    for i in rest[:2]:
        male = float(small_db.subjects["sex"][row[i]] == "male")
        alone = evaluate(mset, small_db.mesh(i), small_db.faces, age_years=small_db.subjects["age_years"][row[i]],
                         male=male)
        assert float(rows[i]["waist_girth_cm"]) == pytest.approx(alone["waist_girth"].value * 100, abs=1e-3)
        assert float(rows[i]["mass_kg"]) == pytest.approx(alone["mass"].value, abs=1e-3)
        assert rows[i]["unposed_deg"] == "0.0"
    for i in np.flatnonzero(small_db.scans["pose"] != "rest"):
        same = rest[np.flatnonzero(small_db.scans["subject"][rest] == small_db.scans["subject"][i])[0]]
        assert float(rows[i]["unposed_deg"]) > 5
        assert abs(float(rows[i]["stature_cm"]) - float(rows[same]["stature_cm"])) < 2.0


def _per_body(db, i, mset, rig):
    """Scan ``i`` measured as ``bodyspace measure MESH`` does it: unposed by the fit, then measured."""
    from bodyspace.rig.unpose import unpose
    row = db.scan_subject_index()[i]
    rest = unpose(db.mesh(i), rig)[0] if db.scans["pose"][i] != "rest" else db.mesh(i)
    return evaluate(mset, rest, db.faces, age_years=db.subjects["age_years"][row],
                    male=float(db.subjects["sex"][row] == "male"))


def test_measure_database_equals_the_per_body_path(small_db, template, tmp_path):
    """Posed scans are unposed with their recorded rotations (exact inverse skinning): every
    value equals the subject's rest scan to 0.01 mm, and the per-body path's (pose fitted from the
    mesh) to 0.1 mm, except shoulder width and size, where the fit itself is up to 1 mm off (the
    clavicle chain is weakly determined by the skin). A database whose recorded rotations do not
    explain its scans falls back to that fit, and gives the per-body path's values."""
    import shutil

    mset, rig = load_measurement_set(), template.rigs["default"]
    out = tmp_path / "m.csv"
    assert runner.invoke(app, ["measure", str(small_db.folder), "--csv", str(out)]).exit_code == 0
    rows = _rows(out)
    names = [m["name"] for m in mset.measurements if m["unit"] == "m"]
    loose = {"shoulder_width", "shoulder_size"}
    scans = small_db.scans
    posed = np.flatnonzero(scans["pose"] != "rest")[:3]
    alone = {i: _per_body(small_db, i, mset, rig) for i in posed}
    for i in posed:
        rest = np.flatnonzero((scans["subject"] == scans["subject"][i]) & (scans["pose"] == "rest"))[0]
        for name in names:
            got, want = rows[i][f"{name}_cm"], alone[i][name].value * 100
            assert (got == "") == (not np.isfinite(want)) == (rows[rest][f"{name}_cm"] == ""), (i, name)
            if got:
                assert float(got) == pytest.approx(float(rows[rest][f"{name}_cm"]), abs=0.001), (i, name)
                assert float(got) == pytest.approx(want, abs=0.1 if name in loose else 0.01), (i, name)
    # Rotations that posed other scans: each scan is fitted instead, as the per-body path does.
    copy = tmp_path / "swapped"
    shutil.copytree(small_db.folder, copy)
    rot = np.load(copy / "rotations.npy")
    moved = np.flatnonzero(scans["pose"] != "rest")           # (all-zero rotations would mean "standing")
    rot[moved] = rot[np.roll(moved, 1)]
    np.save(copy / "rotations.npy", rot)
    out2 = tmp_path / "m2.csv"
    result = runner.invoke(app, ["measure", str(copy), "--csv", str(out2)])
    assert result.exit_code == 0, result.output
    swapped = _rows(out2)
    for i in posed:
        for name in names:
            if swapped[i][f"{name}_cm"]:
                assert float(swapped[i][f"{name}_cm"]) == pytest.approx(alone[i][name].value * 100,
                                                                        abs=0.1 if name in loose else 0.01)


def test_measure_database_as_posed_and_refusals(small_db, tmp_path):
    out = tmp_path / "posed.csv"
    result = runner.invoke(app, ["measure", str(small_db.folder), "--csv", str(out), "--as-posed"])
    assert result.exit_code == 0, result.output
    rows = _rows(out)
    assert len(rows) == 18 and "unposed_deg" not in rows[0]
    # Refused, in the words of the flags: no file, JSON, units, an existing file.
    for args, words in ((["--csv"], "--csv FILE"), (["--json"], "--json does not apply"),
                        (["--csv", str(tmp_path / "u.csv"), "--units", "cm"], "--units does not apply"),
                        (["--csv", str(out)], "already exists")):
        result = runner.invoke(app, ["measure", str(small_db.folder)] + args)
        assert result.exit_code == 2 and words in result.output and "Traceback" not in result.output, args
    assert not (tmp_path / "u.csv").exists()


def test_krylov_pca_reads_codes_from_disk_like_memory(tmp_path, monkeypatch):
    """The Krylov PCA of codes in a RowFile (read in blocks of a few rows) is the in-memory one:
    same captured variance, same components."""
    from bodyspace.rowfile import RowFile
    from bodyspace.shape import ShapeSpace
    from bodyspace.shape import solvers

    rng = np.random.default_rng(0)
    scales = 1.0 / (1 + np.arange(40)) ** 1.5
    codes = ((rng.standard_normal((120, 40)) * scales) @ rng.standard_normal((40, 900))
             + 0.01 * rng.standard_normal((120, 900)) + 3.0).astype(np.float32)
    on_disk = RowFile.create(tmp_path / "codes.npy", codes.shape, np.float32)
    for s in range(0, len(codes), 7):
        on_disk.write(s, codes[s:s + 7])
    np.testing.assert_array_equal(np.load(tmp_path / "codes.npy"), codes)
    monkeypatch.setattr(solvers, "DISK_BLOCK_BYTES", 4 * 900 * 5)  # blocks of 5 rows: 24 of them
    memory = ShapeSpace(n_components=8, solver="krylov", rng=3).fit(codes)
    disk = ShapeSpace(n_components=8, solver="krylov", rng=3).fit(on_disk)
    np.testing.assert_allclose(disk.mean_, memory.mean_, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(disk.explained_variance_ratio_, memory.explained_variance_ratio_, rtol=1e-4)
    np.testing.assert_allclose(np.abs(np.sum(disk.components_ * memory.components_, axis=1)), 1.0, atol=1e-4)
    exact = ShapeSpace(n_components=8, solver="full").fit(codes.astype(np.float64))
    np.testing.assert_allclose(disk.explained_variance_ratio_.sum(), exact.explained_variance_ratio_.sum(), rtol=1e-3)


def test_build_with_codes_on_disk_matches_memory(small_db, tmp_path):
    """BodyModel.fit with the codes on disk (out of core) captures the variance the in-memory
    Krylov fit does, and leaves no code file behind."""
    from bodyspace.model import BodyModel

    kw = dict(encoding="vertex", selection="all", n_components=5, pca_solver="krylov", scratch=tmp_path)
    disk = BodyModel.fit(small_db, codes_on_disk=True, **kw)
    memory = BodyModel.fit(small_db, codes_on_disk=False, **kw)
    assert disk.provenance["codes_on_disk"] and not memory.provenance["codes_on_disk"]
    np.testing.assert_allclose(disk.space.explained_variance_ratio_, memory.space.explained_variance_ratio_,
                               rtol=1e-4)
    assert list(tmp_path.iterdir()) == []


def test_build_resumes_encoding_after_an_interruption(small_db, tmp_path, monkeypatch):
    """An out-of-core build stopped while encoding continues from its last complete chunk and
    fits what an uninterrupted build fits; a build of other inputs starts cleanly and removes the
    stale codes; a finished build leaves nothing in the scratch folder."""
    from bodyspace import model as model_module
    from bodyspace.model import BodyModel

    monkeypatch.setattr(model_module, "ENCODE_BATCH", 4)
    kw = dict(encoding="vertex", selection="all", n_components=5, pca_solver="krylov", scratch=tmp_path)

    def stop_after_8(message, fraction):
        if message.startswith("encoded 8/"):
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        BodyModel.fit(small_db, progress=stop_after_8, **kw)
    assert sorted(p.suffix for p in tmp_path.iterdir()) == [".json", ".lock", ".npy"]
    lines = []
    resumed = BodyModel.fit(small_db, log=lines.append, **kw)
    assert len(lines) == 1 and lines[0].startswith("encoding: resumed an interrupted run from its last complete "
                                                   "chunk: 8 of 18 rows were already computed")
    assert list(tmp_path.iterdir()) == []
    whole = BodyModel.fit(small_db, **kw)
    np.testing.assert_allclose(resumed.space.explained_variance_, whole.space.explained_variance_, rtol=1e-6)
    np.testing.assert_allclose(resumed.space.components_, whole.space.components_, atol=1e-6)

    with pytest.raises(KeyboardInterrupt):
        BodyModel.fit(small_db, progress=stop_after_8, **kw)
    lines = []
    BodyModel.fit(small_db, log=lines.append, **{**kw, "selection": "rest", "n_components": 3})
    assert lines[0].startswith("encoding: started cleanly (removed an interrupted run of other inputs")
    assert list(tmp_path.iterdir()) == []
