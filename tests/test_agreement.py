"""ISO 20685-1's categories and its protocol (measure/tolerances.py, measure/agreement.py; issue 15):
numbers checked by hand."""

import json

import numpy as np
import pytest

from bodyspace.data.template import load_template
from bodyspace.errors import ParameterError
from bodyspace.measure.agreement import agreement, format_agreement
from bodyspace.measure.definitions import load_measurement_set, measurement_set_from_dict
from bodyspace.measure.evaluate import Measurement
from bodyspace.measure.tolerances import (BREADTH, DEPTH, HEIGHT, LARGE_CIRCUMFERENCE, NO_ISO, SEGMENT_LENGTH,
                                          SMALL_CIRCUMFERENCE, iso_categories, iso_category, iso_tolerance)


def test_the_shipped_sets_categories():
    cats = iso_categories(load_measurement_set())
    assert {n for n, c in cats.items() if c == HEIGHT} == {"stature", "height", "crotch_height", "inside_leg_length",
                                                           "leg_length"}
    assert {n for n, c in cats.items() if c == LARGE_CIRCUMFERENCE} == {
        "chest_girth", "underbust_girth", "waist_girth", "hip_girth",
        "breast_size", "waist_size", "hip_size", "shoulder_size"}      # Rupprecht's rings go round the trunk
    assert {n for n, c in cats.items() if c == SMALL_CIRCUMFERENCE} == {
        "neck_girth", *(f"{g}_girth_{s}" for g in ("thigh", "calf", "upper_arm", "wrist") for s in "lr")}
    assert cats["shoulder_width"] == BREADTH
    assert {n for n, c in cats.items() if c == SEGMENT_LENGTH} == {"arm_length_l", "arm_length_r",
                                                                   "leg_length_l", "leg_length_r"}
    assert {n for n, c in cats.items() if c == NO_ISO} == {"volume", "surface_area", "mass", "bmi"}


def test_a_users_own_definitions_get_categories_by_the_rule():
    lm = {"a": [0.0, 1.0, 0.0], "b": [0.3, 1.05, 0.0], "c": [0.0, 1.0, 0.25], "d": [0.1, 0.5, 0.05]}
    assert iso_category({"name": "x", "method": "distance", "from": "a", "to": "b", "unit": "m"}, landmarks=lm) == BREADTH
    assert iso_category({"name": "x", "method": "distance", "from": "a", "to": "c", "unit": "m"}, landmarks=lm) == DEPTH
    assert iso_category({"name": "x", "method": "distance", "from": "a", "to": "d", "unit": "m"},
                        landmarks=lm) == SEGMENT_LENGTH
    # Without a body: a left-right pair of one landmark name is a breadth, other distances segment lengths.
    assert iso_category({"name": "x", "method": "distance", "from": "knee_l", "to": "knee_r", "unit": "m"}) == BREADTH
    assert iso_category({"name": "x", "method": "distance", "from": "knee_l", "to": "hip_r", "unit": "m"}) == SEGMENT_LENGTH
    assert iso_category({"name": "x", "method": "distance", "from": "a", "to": "floor", "axis": "up",
                         "unit": "m"}) == HEIGHT
    assert iso_category({"name": "x", "method": "slice", "part": "forearm_l", "unit": "m"}) == SMALL_CIRCUMFERENCE
    assert iso_category({"name": "x", "method": "slice", "part": ["torso", "thigh_l"], "unit": "m"}) == LARGE_CIRCUMFERENCE
    parts = np.array([9, 9, 9, 0, 0], dtype=np.int8)        # a ring mostly on the left thigh (PARTS[9])
    assert iso_category({"name": "x", "method": "loop", "vertices": [0, 1, 2, 3], "unit": "m"},
                        vertex_parts=parts) == SMALL_CIRCUMFERENCE
    assert iso_category({"name": "x", "method": "volume", "unit": "m^3"}) == NO_ISO
    # A set with its own landmarks, measured on the template's mean body: the direction decides.
    template_set = load_measurement_set()
    d = {"landmarks": {n: template_set.to_dict()["landmarks"][n] for n in ("shoulder_l", "shoulder_r", "head_top")},
         "measurements": [{"name": "across", "method": "distance", "from": "shoulder_l", "to": "shoulder_r"},
                          {"name": "slant", "method": "distance", "from": "shoulder_l", "to": "head_top"}]}
    cats = iso_categories(measurement_set_from_dict(d), load_template())
    assert cats == {"across": BREADTH, "slant": SEGMENT_LENGTH}


def test_iso_tolerance_keeps_its_callers():
    m = Measurement("shoulder_width", 0.4, "m", "distance")
    assert iso_tolerance("shoulder_width", m) == (0.004, False)          # a breadth: 4 mm (was 5)
    assert iso_tolerance("breast_size", Measurement("breast_size", 1.0, "m", "loop")) == (0.009, False)
    assert iso_tolerance("volume", Measurement("volume", 0.07, "m^3", "volume")) == (0.01, True)
    assert iso_tolerance("mine", Measurement("mine", 0.3, "m", "slice")) == (0.004, False)
    assert iso_tolerance("mine", m, category=DEPTH) == (0.005, False)


def test_protocol_by_hand():
    # Errors of 5 subjects (mm): mean 3, SD √2.5 = 1.581, half-width 1.96·1.581/√5 = 1.386:
    # CI [1.614, 4.386]. A height (±4 mm) is refused, a large circumference (±9 mm) accepted.
    col = np.array([1.0, 2.0, 3.0, 4.0, 5.0]) / 1000.0
    err = np.stack([col, col, -col / 10.0, [0.001, np.nan, np.nan, np.nan, np.nan]], axis=1)
    rows = agreement(err, ["h", "c", "b", "lonely"], [HEIGHT, LARGE_CIRCUMFERENCE, BREADTH, HEIGHT])
    h, c, b, lonely = rows
    assert h.n == 5 and h.mean == pytest.approx(0.003) and h.sd == pytest.approx(np.sqrt(2.5) / 1000)
    assert (h.ci_low, h.ci_high) == pytest.approx((0.003 - 0.0013859, 0.003 + 0.0013859), abs=1e-7)
    assert not h.accepted and h.reason.startswith("biased: the interval excludes 0")
    assert c.accepted and c.allowable == 0.009
    assert b.accepted and b.ci_high == pytest.approx(-0.0003 + 0.00013859, abs=1e-8)
    assert lonely.n == 1 and not lonely.accepted and "needs 2" in lonely.reason
    # A bias beyond the allowable error: refused as biased.
    biased = agreement(np.full((4, 1), 0.005) + [[0.0], [0.0001], [0.0], [-0.0001]], ["s"], [HEIGHT])[0]
    assert not biased.accepted and biased.reason.startswith("biased: the whole interval")
    spread = agreement(np.array([[0.004], [-0.004], [0.0]]), ["s"], [HEIGHT])[0]
    assert not spread.accepted and spread.reason.startswith("spread")
    # Relative categories: errors divided by the reference (1 % of the value).
    ref = np.array([[70.0], [80.0], [100.0]])
    vol = agreement(np.array([[0.35], [0.4], [0.5]]), ["mass"], [NO_ISO], reference=ref)[0]
    assert vol.relative and vol.mean == pytest.approx(0.005) and vol.sd == pytest.approx(0.0) and vol.accepted
    text = format_agreement(rows)
    assert "REJECTED" in text and "accepted for 2 of 4" in text and "+3.0" in text


def test_protocol_refuses_bad_input():
    with pytest.raises(ParameterError, match="one name and one category"):
        agreement(np.zeros((3, 2)), ["a"], [HEIGHT])
    with pytest.raises(ParameterError, match="unknown 'tiny'"):
        agreement(np.zeros((3, 1)), ["a"], ["tiny"])
    with pytest.raises(ParameterError, match="reference"):
        agreement(np.zeros((3, 1)), ["mass"], [NO_ISO])


def test_cli_agreement(tmp_path):
    """`bodyspace agreement`: subjects matched by id (one file's extra subject left out), cm and mm
    columns, a user's own measurement given a category, the verdicts printed and written."""
    from typer.testing import CliRunner

    from bodyspace.cli import app
    runner = CliRunner()
    scans = tmp_path / "scans.csv"
    tape = tmp_path / "tape.csv"
    # waist (large, ±0.9 cm): errors 0.1, 0.2, 0.3 cm → accepted; stature in mm: errors 1..3 mm,
    # mean 2, SD 1, CI 2 ± 1.13 → [0.87, 3.13] mm within ±4 → accepted; thumb (own, small, ±0.4 cm):
    # errors 1 cm each → biased, rejected.
    scans.write_text("subject,waist_girth_cm,stature_mm,thumb_cm\na,80.1,1701,6\nb,90.2,1802,7\nc,70.3,1603,8\n"
                     "z,1,1,1\n")
    tape.write_text("subject,waist_girth_cm,stature_mm,thumb_cm\nc,70,1600,7\nb,90,1800,6\na,80,1700,5\n")
    out = tmp_path / "agreement.json"
    r = runner.invoke(app, ["agreement", str(scans), str(tape), "--category", "thumb=small", "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "3 subjects in both files (1 in one only" in r.output and "accepted for 2 of 3" in r.output
    doc = json.loads(out.read_text())
    rows = {m["name"]: m for m in doc["measurements"]}
    assert rows["waist_girth"]["accepted"] and rows["waist_girth"]["mean"] == pytest.approx(0.2)
    assert rows["stature"]["category"] == HEIGHT and rows["stature"]["ci_high"] == pytest.approx(0.2 + 0.1131596, abs=1e-4)
    assert not rows["thumb"]["accepted"] and rows["thumb"]["reason"].startswith("biased")
    bad = runner.invoke(app, ["agreement", str(scans), str(tape)])
    assert bad.exit_code != 0 and "--category thumb=" in bad.output
