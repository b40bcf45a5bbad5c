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
from bodyspace.synth.population import (
    MOMENT_TOL,
    build_population,
    describe_redraws,
    draw_subjects,
    load_survey,
    redraw_report,
    sample_subjects,
    solve_subjects,
    target_moments,
)


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


def test_unreachable_subject_is_redrawn_deterministically(phenotype_model):
    """A target the body model cannot reach (a woman of BMI 40: MakeHuman's heaviest woman is ~33)
    is redrawn from the seed; the others are solved as drawn, and the output says what moved."""
    def forced():
        draw = draw_subjects(12, rng=4)
        draw.target_bmi[woman] = 40.0
        draw.drawn_moments = target_moments(draw.male, draw.target_stature_m, draw.target_bmi)
        return draw, solve_subjects(phenotype_model, draw, np.arange(12))

    plain = draw_subjects(12, rng=4)
    woman = int(np.flatnonzero(~plain.male)[1])
    draw, (h, _, _, bmi, _) = forced()
    report = redraw_report(draw)
    assert report["redrawn"] == 1 and report["subjects"] == [woman] and draw.redrawn[woman] >= 1
    # The replacement is reachable and reached; it is a woman with a survey-like BMI.
    assert not draw.male[woman] and draw.target_bmi[woman] < 35
    assert np.abs(h - draw.target_stature_m).max() < 2e-4 and np.abs(bmi - draw.target_bmi).max() < 1e-2
    # Everyone else keeps the targets drawn for them.
    others = np.arange(12) != woman
    np.testing.assert_array_equal(draw.target_bmi[others], plain.target_bmi[others])
    np.testing.assert_array_equal(draw.target_stature_m[others], plain.target_stature_m[others])
    # Deterministic: the same seed gives the same replacement.
    again, _ = forced()
    np.testing.assert_array_equal(again.phenotypes, draw.phenotypes)
    # The report's moments are those of the targets, before and after; the men did not move.
    after = target_moments(draw.male, draw.target_stature_m, draw.target_bmi)
    assert report["moments"]["female"]["bmi_mean"] == [draw.drawn_moments["female"]["bmi_mean"],
                                                       after["female"]["bmi_mean"]]
    assert all(b == a for b, a in report["moments"]["male"].values())
    line = describe_redraws(report)
    assert line.startswith("1 subject(s) redrawn") and "female stature mean" in line


def test_redraw_keeps_moments_of_a_large_population(phenotype_model):
    """In a population of 1,000 women one redraw moves the moments by less than the survey bar
    (MOMENT_TOL: 0.1 cm, 0.05 BMI): of the reachable candidates the least-moving one is chosen."""
    draw = draw_subjects(2000, rng=5)
    woman = int(np.flatnonzero(~draw.male)[0])
    draw.target_bmi[woman] = 36.0
    draw.drawn_moments = target_moments(draw.male, draw.target_stature_m, draw.target_bmi)
    solve_subjects(phenotype_model, draw, np.array([woman]))
    report = redraw_report(draw)
    assert report["subjects"] == [woman]
    for name, (before, after) in report["moments"]["female"].items():
        assert abs(after - before) < MOMENT_TOL[name], name


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


def _population_bytes(folder):
    return {name: (folder / name).read_bytes() for name in ("vertices.npy", "rotations.npy", "subjects.csv",
                                                             "scans.csv", "faces.npy")}


def _children(pid):
    """Process ids of ``pid``'s children (Linux /proc)."""
    import pathlib
    return {int(c) for task in pathlib.Path(f"/proc/{pid}/task").iterdir()
            for c in (task / "children").read_text().split()}


def test_build_population_resumes_after_a_kill(template, tmp_path):
    """A run of two worker processes killed (SIGKILL) after some chunks is resumed from its last
    complete chunk and writes the same database as an uninterrupted run in one process; the
    folder never exists half-written and the killed run's workers die with it."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from bodyspace.synth.population import STATE_FILE, unfinished_folder

    whole = tmp_path / "whole"
    build_population(template, whole, n_subjects=10, n_poses=1, rng=9, chunk=2, workers=1)
    out = tmp_path / "killed"
    work = unfinished_folder(out)
    # The child runs the same population slowed down after each chunk so the kill lands between chunks.
    code = ("import time, sys; from bodyspace.data.template import load_template; "
            "from bodyspace.synth.population import build_population; "
            f"build_population(load_template(), {str(out)!r}, 10, 1, rng=9, chunk=2, workers=2, "
            "progress=lambda m, f: time.sleep(0.5) if m.startswith('wrote') else None)")
    child = subprocess.Popen([sys.executable, "-c", code], env=dict(os.environ))
    deadline = time.time() + 120
    while time.time() < deadline and not (work / STATE_FILE).is_file():
        time.sleep(0.05)
    workers = _children(child.pid)
    child.send_signal(signal.SIGKILL)
    child.wait()
    assert (work / STATE_FILE).is_file() and not out.exists()
    assert len(workers) == 2
    deadline = time.time() + 30
    while time.time() < deadline and any(os.path.exists(f"/proc/{w}") for w in workers):
        time.sleep(0.05)
    assert not any(os.path.exists(f"/proc/{w}") for w in workers), "a worker outlived its killed parent"
    lines = []
    build_population(template, out, n_subjects=10, n_poses=1, rng=9, chunk=2, log=lines.append, workers=2)
    assert lines[0].startswith("resumed an interrupted run from its last complete chunk")
    assert not work.exists()
    assert _population_bytes(out) == _population_bytes(whole)
    assert sorted(p.name for p in out.iterdir()) == sorted(p.name for p in whole.iterdir())


def test_build_population_same_bytes_for_any_number_of_workers(template, tmp_path, monkeypatch):
    """Two subjects in different chunks are out of reach (BMI 40 women): each is redrawn the same
    way whether one process or two make the chunks, so the databases are byte for byte equal."""
    import bodyspace.synth.population as population

    seed_draw = population.draw_subjects

    def unreachable_women(n, rng=None, survey="ansur1988"):
        draw = seed_draw(n, rng, survey)
        for woman in np.flatnonzero(~draw.male)[[0, -1]]:
            draw.target_bmi[woman] = 40.0
        draw.drawn_moments = target_moments(draw.male, draw.target_stature_m, draw.target_bmi)
        return draw

    monkeypatch.setattr(population, "draw_subjects", unreachable_women)
    lines = {}
    for workers in (1, 2):
        lines[workers] = []
        build_population(template, tmp_path / f"w{workers}", n_subjects=6, n_poses=0, rng=6, chunk=2,
                         workers=workers, log=lines[workers].append)
    assert _population_bytes(tmp_path / "w1") == _population_bytes(tmp_path / "w2")
    assert lines[1] == lines[2] and lines[2][1].startswith("2 subject(s) redrawn")
    meta = json.loads((tmp_path / "w2" / "meta.json").read_text())
    assert len(meta["provenance"]["redrawn_subjects"]) == 2


def test_build_population_starts_cleanly_over_another_request(template, tmp_path):
    """An unfinished run of other parameters is not resumed: it is removed and the run says so."""
    from bodyspace.synth.population import unfinished_folder

    out = tmp_path / "db"

    def stop_after_first_chunk(message, fraction):
        if message.startswith("wrote"):
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        build_population(template, out, n_subjects=6, n_poses=0, rng=1, chunk=2, progress=stop_after_first_chunk)
    assert unfinished_folder(out).is_dir() and not out.exists()
    lines = []
    db = build_population(template, out, n_subjects=6, n_poses=0, rng=2, chunk=2, log=lines.append)
    assert lines[0].startswith("started cleanly (removed the unfinished run") and "another request" in lines[0]
    assert db.n_scans == 6 and not unfinished_folder(out).exists()
    assert lines[1].startswith("no subject redrawn")


def test_remaining_time_is_the_rate_of_the_run_since_its_first_report():
    from bodyspace.cli.common import remaining_seconds

    assert remaining_seconds((3.0, 0.0), (3.0, 0.0)) is None  # no rate yet
    # 10 s for the first 10 % of the work: 90 s left (start-up before the first report not counted).
    assert remaining_seconds((5.0, 0.0), (15.0, 0.1)) == pytest.approx(90.0)
    # A resumed run reports 60 % first: that jump is not speed; 10 s for the next 10 % leaves 30 s.
    assert remaining_seconds((100.0, 0.6), (110.0, 0.7)) == pytest.approx(30.0)
    assert remaining_seconds((0.0, 0.0), (50.0, 1.0)) == 0.0
