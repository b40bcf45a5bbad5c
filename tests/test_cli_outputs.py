"""The command line's safe doors: the output policy (refuse, --force replaces only bodyspace's own
outputs, leftovers of killed runs removed, umask honoured, atomic demo), --version, help on every
option, and bad inputs that end in one clear line and exit 2 instead of a traceback."""

import concurrent.futures
import json
import os
import signal
import stat
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import typer
import typer.main
from typer.testing import CliRunner

from bodyspace import __version__
from bodyspace.atomic import MARKER, is_own_file, remove_leftovers
from bodyspace.cli import app
from bodyspace.cli import model as cli_model
from bodyspace.cli.common import guarded
from bodyspace.model import BodyModel
from bodyspace.synth.population import build_population

runner = CliRunner()
SRC = str(Path(__file__).resolve().parents[1] / "src")


@pytest.fixture(scope="module")
def tiny(template, tmp_path_factory):
    """A 6-subject rest-pose database and its vertex model (seconds to make)."""
    root = tmp_path_factory.mktemp("outputs")
    db = build_population(template, root / "db", 6, 0, rng=0)
    model = BodyModel.fit(db, "vertex", "rest", template=template)
    model.save(root / "model.npz")
    return root


def run(*args):
    result = runner.invoke(app, [str(a) for a in args])
    assert "Traceback" not in result.output, result.output
    if result.exit_code != 0:
        assert isinstance(result.exception, SystemExit), repr(result.exception)
    return result


def refused(result, *words):
    """Exit 2 with one ``error:`` line that contains every one of ``words``."""
    assert result.exit_code == 2, result.output
    lines = [ln for ln in result.output.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1, result.output
    text = " ".join(result.output.split())
    for w in words:
        assert w in text, (w, result.output)
    return text


def dead_pid() -> int:
    """The id of a process that has just ended."""
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


# ----------------------------------------------------------------------------- version and help
def test_version():
    r = run("--version")
    assert r.exit_code == 0 and r.output.strip() == f"bodyspace {__version__}"


def _commands(group, path=()):
    """(path, command) of a Typer app's click command tree (typer vendors click: no import).
    ``get_command`` loads a lazily loaded command (bodyspace.cli.LazyGroup); ``commands`` would
    hold its stand-in."""
    yield path, group
    if hasattr(group, "list_commands"):
        for name in group.list_commands(None):
            yield from _commands(group.get_command(None, name), path + (name,))


def test_every_option_of_every_command_has_help():
    root = typer.main.get_command(app)
    missing, n = [], 0
    for path, cmd in _commands(root):
        for p in cmd.params:
            n += 1
            if not (getattr(p, "help", None) or "").strip():
                missing.append(f"{' '.join(path) or 'bodyspace'} {p.name}")
    assert n > 60 and not missing, missing


def test_python_dash_m_and_version_in_a_fresh_process():
    r = subprocess.run([sys.executable, "-m", "bodyspace", "--version"], capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": SRC}, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == f"bodyspace {__version__}", r.stderr


# ----------------------------------------------------------------------------- folders
def test_folder_output_refused_then_replaced_only_when_ours(tiny, tmp_path):
    model = tiny / "model.npz"
    out = tmp_path / "s"
    assert run("sample", model, "-n", "2", "--out", out, "--no-png").exit_code == 0
    marker = json.loads((out / MARKER).read_text())
    assert marker["written_by"] == "bodyspace" and marker["kind"] == "samples"
    assert marker["entries"] == ["body_000.obj", "body_001.obj"]
    refused(run("sample", model, "-n", "2", "--out", out), "--out", "already exists", "--force")
    assert run("sample", model, "-n", "3", "--out", out, "--force", "--no-png").exit_code == 0
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "body_000.obj", "body_001.obj", "body_002.obj"]
    # a file the user put into our folder: --force would delete it, so it refuses
    (out / "notes.txt").write_text("mine")
    refused(run("sample", model, "-n", "2", "--out", out, "--force"), "notes.txt", "did not write")
    assert (out / "notes.txt").read_text() == "mine" and (out / "body_002.obj").exists()
    # a folder bodyspace did not write, and one of another kind
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "thesis.tex").write_text("years of work")
    refused(run("sample", model, "-n", "2", "--out", foreign, "--force"), "not written by bodyspace")
    refused(run("population", "--subjects", "2", "--out", foreign, "--force"), "not written by bodyspace")
    refused(run("demo", "--out", foreign, "--force", "--subjects", "2"), "not written by bodyspace")
    assert [p.name for p in foreign.iterdir()] == ["thesis.tex"]
    refused(run("sample", model, "-n", "2", "--out", tiny / "db", "--force"), "'database'", "same kind")
    assert (tiny / "db" / "vertices.npy").exists()


def test_population_refuses_before_the_work(tmp_path):
    out = tmp_path / "db"
    out.mkdir()
    (out / "x").write_text("x")
    text = refused(run("population", "--subjects", "2", "--out", out), "--out", "--force")
    assert "overwrite=True" not in text and "writing the database" not in text
    refused(run("population", "--subjects", "2", "--poses", "1000", "--out", tmp_path / "p"), "--poses 1000", "38")
    refused(run("demo", "--subjects", "2", "--poses", "1000", "--out", tmp_path / "d"), "--poses 1000", "38")
    assert not (tmp_path / "p").exists() and not (tmp_path / "d").exists()


def test_library_overwrite_replaces_only_bodyspace_databases(tiny, tmp_path):
    from bodyspace.data.database import ScanDatabase
    from bodyspace.errors import BodyspaceError
    db = ScanDatabase.load(tiny / "db")
    target = tmp_path / "copy"
    db.save(target)
    db.save(target, overwrite=True)  # ours: replaced
    assert ScanDatabase.load(target).n_scans == db.n_scans
    other = tmp_path / "other"
    other.mkdir()
    (other / "data.csv").write_text("1,2\n")
    with pytest.raises(BodyspaceError, match="not written by bodyspace"):
        db.save(other, overwrite=True)
    assert (other / "data.csv").read_text() == "1,2\n"


# ----------------------------------------------------------------------------- files
def test_file_outputs_replace_only_bodyspace_files(tiny, tmp_path):
    model = tiny / "model.npz"
    before = model.read_bytes()
    assert is_own_file(model)
    mesh = tmp_path / "s" / "body_000.obj"
    assert run("sample", model, "-n", "1", "--out", tmp_path / "s").exit_code == 0
    assert is_own_file(mesh) and is_own_file(tmp_path / "s" / "samples.png")
    # --png onto the model, evaluate --out onto the model: refused, the model untouched
    refused(run("measure", mesh, "--png", model), "--png", ".png")
    refused(run("measure", mesh, "--png", model, "--force"), "--png", ".png")
    refused(run("evaluate", model, "--out", model, "--force"), "--out", ".md")
    refused(run("build", tiny / "db", "--out", model, "--encoding", "vertex"), "--out", "already exists")
    assert model.read_bytes() == before
    # a foreign file with the right suffix: --force still refuses
    fake = tmp_path / "fake.npz"
    fake.write_bytes(b"PK\x03\x04 not ours")
    refused(run("build", tiny / "db", "--out", fake, "--force", "--encoding", "vertex"), "not written by bodyspace")
    assert fake.read_bytes() == b"PK\x03\x04 not ours"
    photo = tmp_path / "photo.png"
    photo.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 30)
    refused(run("measure", mesh, "--png", photo, "--force"), "not written by bodyspace")
    # our own PNG and model: --force replaces them
    assert run("measure", mesh, "--png", tmp_path / "s" / "samples.png", "--force").exit_code == 0
    m2 = tmp_path / "m2.npz"
    assert run("build", tiny / "db", "--out", m2, "--encoding", "vertex").exit_code == 0
    assert run("build", tiny / "db", "--out", m2, "--encoding", "vertex", "--force").exit_code == 0
    assert BodyModel.load(m2).n_components == BodyModel.load(model).n_components


@pytest.mark.parametrize("where, words, folder_too", [
    (".", ["--out .", "names an existing folder"], True),
    ("FOLDER", ["is a folder"], False),
    ("FILE/child.npz", ["is a file, not a folder"], True),
    ("/proc/bodyspace/m.npz", ["cannot write in /proc"], True),
    ("m.txt", ["ending in .npz"], False),
])
def test_bad_output_paths_are_one_line(tiny, tmp_path, monkeypatch, where, words, folder_too):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "FOLDER").mkdir()
    (tmp_path / "FILE").write_text("x")
    refused(run("build", tiny / "db", "--out", where, "--encoding", "vertex"), *words)
    if folder_too:
        refused(run("population", "--subjects", "2", "--out", where), *words)
        refused(run("sample", tiny / "model.npz", "--out", where), *words)
    refused(run("population", "--subjects", "2", "--out", "FILE"), "is a file, expected a folder")


# ----------------------------------------------------------------------------- leftovers, umask
def test_leftovers_of_killed_runs_are_removed_and_nothing_else(tiny, tmp_path):
    dead, alive = dead_pid(), os.getppid()
    stale_dir = tmp_path / f".s.bodyspace-{dead}-0123abcd.part"
    stale_dir.mkdir()
    (stale_dir / "vertices.npy").write_bytes(b"\0" * 1000)
    stale_file = tmp_path / f".m.npz.bodyspace-{dead}-89abcdef.part"
    stale_file.write_bytes(b"half a model")
    running = tmp_path / f".x.bodyspace-{alive}-00000000.part"
    running.mkdir()
    others = [tmp_path / ".s.a1b2c3d4.part", tmp_path / f".s.{dead}.part", tmp_path / "keep.part"]
    for p in others:
        p.write_text("not ours")
    assert run("sample", tiny / "model.npz", "-n", "1", "--out", tmp_path / "s", "--no-png").exit_code == 0
    assert not stale_dir.exists() and not stale_file.exists()
    assert running.exists() and all(p.exists() for p in others)
    assert remove_leftovers(tmp_path) == []


def test_outputs_honour_the_umask(tiny, tmp_path):
    old = os.umask(0o002)
    try:
        assert run("sample", tiny / "model.npz", "-n", "1", "--out", tmp_path / "s").exit_code == 0
        assert run("build", tiny / "db", "--out", tmp_path / "m.npz", "--encoding", "vertex").exit_code == 0
    finally:
        os.umask(old)
    mode = lambda p: stat.S_IMODE(p.stat().st_mode)
    assert mode(tmp_path / "s") == 0o775
    assert mode(tmp_path / "s" / "body_000.obj") == 0o664 and mode(tmp_path / "s" / "samples.png") == 0o664
    assert mode(tmp_path / "m.npz") == 0o664


def test_a_killed_demo_leaves_no_folder_and_the_next_run_cleans_up(template, tmp_path):
    out = tmp_path / "demo"
    env = {**os.environ, "PYTHONPATH": SRC}
    proc = subprocess.Popen([sys.executable, "-m", "bodyspace", "demo", "--out", str(out), "--subjects", "2",
                             "--poses", "0"], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    try:
        while not list(tmp_path.glob(".demo.bodyspace-*.part/population")) and time.monotonic() < deadline:
            assert proc.poll() is None, "the demo ended before it could be killed"
            time.sleep(0.1)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    parts = list(tmp_path.glob(".demo.bodyspace-*.part"))
    assert len(parts) == 1 and not out.exists()
    assert remove_leftovers(tmp_path) == parts and not parts[0].exists()


# ----------------------------------------------------------------------------- errors and silent drops
def test_bad_numbers_name_their_flag(tiny, tmp_path):
    r = run("sample", tiny / "model.npz", "--seed", "-1", "--out", tmp_path / "s")
    assert r.exit_code == 2 and "--seed" in r.output
    refused(run("sample", tiny / "model.npz", "--components", "99", "--out", tmp_path / "s"), "--components 99")
    refused(run("sample", tiny / "model.npz", "--format", "stl", "--out", tmp_path / "s"), "--format", "obj")
    refused(run("build", tiny / "db", "--out", tmp_path / "m.npz", "--on-flipped", "banana"), "--on-flipped")
    assert not (tmp_path / "s").exists() and not (tmp_path / "m.npz").exists()


def test_sample_streams_and_says_what_the_sheet_shows(tiny, tmp_path, monkeypatch):
    # small chunk and sheet sizes, so that the streaming path runs in a second
    monkeypatch.setattr(cli_model, "SAMPLE_CHUNK", 2)
    monkeypatch.setattr(cli_model, "SHEET_MAX", 3)
    out = tmp_path / "many"
    r = run("sample", tiny / "model.npz", "-n", "5", "--format", "ply", "--out", out)
    assert r.exit_code == 0 and "first 3" in r.output
    assert len(list(out.glob("body_*.ply"))) == 5
    # the same bodies as BodyModel.sample (one draw, decoded in chunks)
    from bodyspace.mesh.io import load_mesh
    model = BodyModel.load(tiny / "model.npz")
    expected = model.sample(5, sigma_range=2.0, rng=0)
    for i in (0, 4):
        v, _ = load_mesh(out / f"body_00{i}.ply")
        assert np.abs(v - expected[i]).max() < 1e-5


def test_semantic_requests_refuse_repeats_and_suggest_the_right_unit(tiny, tmp_path):
    model = tmp_path / "model.npz"
    model.write_bytes((tiny / "model.npz").read_bytes())
    out = tmp_path / "g.obj"
    r = run("generate", model, "--database", tiny / "db", "--set", "stature=175cm", "--out", out)
    assert r.exit_code == 0, r.output
    refused(run("generate", model, "--set", "stature=175cm", "--out", out), "--out", "--force")
    refused(run("generate", model, "--set", "stature=180cm", "--set", "stature=170cm", "--out", tmp_path / "a.obj"),
            "--set", "twice")
    refused(run("generate", model, "--set", "stature=180cm", "--range", "stature=170:190cm", "--out",
                tmp_path / "a.obj"), "twice")
    text = refused(run("generate", model, "--set", "mass=-3kg", "--out", tmp_path / "a.obj"), "mass=80kg")
    assert "180cm" not in text
    assert not (tmp_path / "a.obj").exists()
    assert run("generate", model, "--set", "stature=170cm", "--out", out, "--force").exit_code == 0
    ev = run("evaluate", model, "--folds", "2")
    assert ev.exit_code == 0, ev.output
    assert is_own_file(tmp_path / "model.evaluation.md") and is_own_file(tmp_path / "model.evaluation.json")
    refused(run("evaluate", model, "--folds", "2"), "--out", "already exists")
    assert run("evaluate", model, "--folds", "2", "--force").exit_code == 0


def test_mapping_shape_refuses_a_miss_unless_accepted(tiny, tmp_path):
    model = tmp_path / "model.npz"
    model.write_bytes((tiny / "model.npz").read_bytes())
    assert run("mapping", "fit", model, "--samples", "300", "--trees", "5").exit_code == 0
    names = BodyModel.load(model).mapping.names
    request = []
    for name in names:
        request += ["--set", f"{name}={'500' if name == 'height' else '90'}cm"]
    out = tmp_path / "b.obj"
    refused(run("mapping", "shape", model, *request, "--out", out), "misses", "--accept-misses")
    assert not out.exists()
    assert run("mapping", "shape", model, *request, "--out", out, "--accept-misses").exit_code == 0
    assert out.exists()
    refused(run("mapping", "shape", model, *request, "--set", "height=170cm", "--out", tmp_path / "c.obj"),
            "--set height", "twice")


def test_the_error_exit_folds_thread_warnings_into_one_line(capsys):
    def noisy():
        def work(x):
            return np.log(np.array([x]))  # RuntimeWarning inside a worker thread
        with concurrent.futures.ThreadPoolExecutor(2) as pool:
            list(pool.map(work, [0.0, -1.0, 0.0, 2.0]))
        warnings.warn("the request was clamped to 195 cm", UserWarning)

    guarded(noisy)()
    err = capsys.readouterr().err
    assert "thread.py" not in err and "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert any("clamped" in ln for ln in lines)
    assert sum("floating-point" in ln for ln in lines) == 1, err


def test_internal_errors_are_one_line_and_exit_3(capsys):
    def broken():
        raise KeyError("x")
    with pytest.raises(typer.Exit) as exc:
        guarded(broken)()
    assert exc.value.exit_code == 3
    err = capsys.readouterr().err
    assert "internal error" in err and "Traceback" not in err
