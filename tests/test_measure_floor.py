"""A scanner's mesh that carries its floor, a turntable or a pole: measured as the body alone
(``conventions.body_faces``), with a note saying what was left out (issue 15, floor24)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from bodyspace.cli import app
from bodyspace.errors import MeasurementError
from bodyspace.measure import conventions as cv
from bodyspace.measure import evaluate, load_measurement_set
from bodyspace.measure.landmark_check import landmark_measurement_set
from bodyspace.mesh.io import save_mesh

from floor_meshes import disc, welded_sheet

runner = CliRunner()


@pytest.fixture(scope="module")
def body(template):
    return np.asarray(template.vertices, float), np.asarray(template.faces)


@pytest.fixture(scope="module")
def lm_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("floor") / "lm.json"
    path.write_text(json.dumps({"landmarks": load_measurement_set().to_dict()["landmarks"]}))
    return path


@pytest.fixture(scope="module")
def lm_set(lm_file):
    return landmark_measurement_set(lm_file, base=load_measurement_set())


@pytest.fixture(scope="module")
def reference(body, lm_set):
    return {k: float(m.value) for k, m in evaluate(lm_set, *body).items()}


def _measured(v, f, mset, units=None):
    got = cv.body_faces(v, f, mset, units)
    vv, ff = cv.prepare(got.vertices, got.faces, mset, units=units)
    return got, {k: float(m.value) for k, m in evaluate(mset, vv, ff).items()}


def test_a_body_alone_is_returned_as_it_was(body, lm_set):
    v, f = body
    got = cv.body_faces(v, f, lm_set)
    assert got.vertices is v and got.faces is f and got.notes == () and not got.welded


def test_separate_floor_and_pole_left_out_exactly(body, lm_set, reference):
    v, f = body
    y0 = v[:, 1].min()
    floor_v, floor_f = disc((0.0, 0.0, v[:, 2].mean()), 0.8, y0)
    pole_v, pole_f = disc((0.75, 0.0, 0.0), 0.02, y0, rings=1, seg=8)
    pole_v = np.r_[pole_v, pole_v + (0, 2.0, 0)]            # a 2 m pole's ends (a stool's legs alike)
    pole_f = np.r_[pole_f, pole_f + len(pole_v) // 2, [[1, 2, 2 + len(pole_v) // 2]]]
    mesh_v = np.r_[v, floor_v, pole_v]
    mesh_f = np.r_[f, floor_f + len(v), pole_f + len(v) + len(floor_v)]
    got, values = _measured(mesh_v * 1000.0, mesh_f, lm_set, "mm")
    assert np.array_equal(got.faces, f)
    assert len(got.notes) == 1 and "left out 2 pieces not joined to the body" in got.notes[0]
    for name in ("stature", "volume", "mass", "waist_girth", "hip_girth", "surface_area"):
        assert values[name] == pytest.approx(reference[name], rel=1e-9), name


def test_welded_floor_cut_and_said(body, lm_set, reference):
    v, f = body
    sheet_v, sheet_f = welded_sheet(v)
    got, values = _measured(sheet_v, np.r_[f, sheet_f], lm_set)   # metres, the unit from the landmarks
    assert got.welded and "the floor" in got.notes[0] and "soles are open" in got.notes[-1]
    assert abs(values["stature"] - reference["stature"]) < 1e-3
    for name in ("volume", "mass", "waist_girth", "hip_girth"):
        assert values[name] == pytest.approx(reference[name], rel=0.005), name


def test_unit_message_never_contradicts_the_unit_given(body, lm_set):
    """Joined geometry that could not be told apart: said as such, not as "is it in mm?"."""
    v, f = body
    big_v, big_f = disc((0.0, 0.0, 0.0), 2.5, v[:, 1].min(), rings=2)
    sheet_v = np.r_[v, big_v]
    sheet_f = np.r_[f, big_f + len(v), [[0, len(v), 1]]]            # one face joins it to the body
    for units in ("mm", None):
        with pytest.raises(MeasurementError) as err:
            cv.prepare(sheet_v * 1000.0, sheet_f, lm_set, units=units)
        msg = str(err.value)
        assert "landmarks span 1.59 m" in msg and "carries more than the body" in msg, msg
        assert "is it in" not in msg and "wound inwards" not in msg and "too large" not in msg
    with pytest.raises(MeasurementError, match="in centimetres, the unit given, it is .*landmarks span 1.59 m in "
                                               "millimetres, a body's size; give units='mm'$"):
        cv.prepare(sheet_v * 1000.0, sheet_f, lm_set, units="cm")


def test_cli_measure_leaves_the_floor_out_and_says_so(body, lm_file, tmp_path, reference):
    v, f = body
    floor_v, floor_f = disc((0.0, 0.0, v[:, 2].mean()), 0.8, v[:, 1].min())
    z_up = cv.UP_ROTATIONS["z"]
    path = tmp_path / "scan.obj"
    save_mesh(path, (np.r_[v, floor_v] @ z_up) * 1000.0, np.r_[f, floor_f + len(v)])
    result = runner.invoke(app, ["measure", str(path), "--landmarks", str(lm_file), "--units", "mm", "--up", "z",
                                 "--json"])
    assert result.exit_code == 0, result.output
    row = json.loads(result.stdout)
    assert row["left_out"]["unit"] == "m^2" and row["left_out"]["value"] == pytest.approx(2.0, abs=0.02)
    assert "left out 1 piece not joined to the body" in row["left_out"]["note"]
    assert row["volume"]["value"] == pytest.approx(reference["volume"], rel=1e-4)
    table = runner.invoke(app, ["measure", str(path), "--landmarks", str(lm_file), "--units", "mm", "--up", "z"])
    assert table.exit_code == 0 and "[left out] scan.obj: left out 1 piece" in " ".join(table.stdout.split())
