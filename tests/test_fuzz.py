"""Fuzz harness: every CLI command and the library doors fed generated bad inputs.

The inputs are in tests/fuzz_inputs.py, one test id each. A case fails on a Python traceback
(an exception other than ``BodyspaceError`` from a library door; on the CLI, run in-process with
typer's CliRunner, an exception other than SystemExit, or "Traceback" in the output), on a raw
Python warning reaching the user, on a run that hangs, and on an exit 0 (or a return) that the
case does not accept or whose result its check rejects.

Cases that fail in code other helpers are restructuring now are marked xfail(strict=True) in
KNOWN_FAILURES with the owner area: when the fix is merged they XPASS, which fails, so the mark
is removed then.
"""

from __future__ import annotations

import os
import shutil
import signal
import warnings
from contextlib import contextmanager
from pathlib import Path

import fuzz_inputs
import numpy as np
import pytest
from fuzz_inputs import Env
from typer.testing import CliRunner

from bodyspace.cli import app
from bodyspace.cli.common import EXIT_INTERNAL_ERROR
from bodyspace.errors import BodyspaceError
from bodyspace.mesh.io import save_mesh
from bodyspace.model import BodyModel
from bodyspace.synth.population import build_population

CASE_SECONDS = 20  # a case that runs longer hangs or does unbounded work for a bad input
KNOWN_FAILURE_SECONDS = 2  # a known failure (xfail) is not waited for
MIN_DISTINCT_INPUTS = 200

CASES = fuzz_inputs.all_cases()

# case id -> "<owner area>: <what happens>" (see the module docstring).
# Empty: every known failure has been fixed; a new one is listed here until its fix lands.
KNOWN_FAILURES: dict[str, str] = {}

runner = CliRunner()


@pytest.fixture(scope="session")
def env(template, tmp_path_factory) -> Env:
    """Good inputs, built once per worker: a 12-subject database, a vertex model with its semantic
    regressors stored in it, the same model without them and their legacy sidecar file, the model
    with a (small) mapping, and one body in four formats."""
    root = tmp_path_factory.mktemp("fuzz-good")
    db = build_population(template, root / "db", 12, 0, rng=0)
    model = root / "model.npz"
    BodyModel.fit(db, "vertex", "rest").save(model)
    body = {".obj": root / "body.obj"}
    fitted = runner.invoke(app, ["generate", str(model), "--database", str(root / "db"), "--set", "stature=172cm",
                                 "--seed", "1", "--out", str(body[".obj"])])
    assert fitted.exit_code == 0, fitted.output
    mapped = root / "mapped.npz"
    fitted = runner.invoke(app, ["mapping", "fit", str(model), "--samples", "150", "--trees", "3", "-o", str(mapped)])
    assert fitted.exit_code == 0, fitted.output
    bare, legacy = root / "bare.npz", root / "legacy.semantics.npz"
    loaded = BodyModel.load(model)
    fuzz_inputs.write_legacy_sidecar(loaded.semantics, legacy)
    loaded.semantics = None
    loaded.save(bare)
    vertices = np.loadtxt([line[2:] for line in body[".obj"].read_text().splitlines() if line.startswith("v ")])
    for suffix in (".ply", ".stl", ".glb"):
        body[suffix] = root / f"body{suffix}"
        save_mesh(body[suffix], vertices, template.faces)
    return Env(root=root, model=model, mapped=mapped, db=root / "db", body=body,
               n_vertices=len(template.vertices), faces=template.faces, bare=bare, legacy_sidecar=legacy)


class CaseTimeout(BaseException):
    """Raised by the alarm: a BaseException, so no ``except Exception`` (or OSError, which
    TimeoutError is) in the code under test can swallow it."""


@contextmanager
def _time_limit(seconds: int):
    def expire(signum, frame):
        raise CaseTimeout(f"still running after {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def _paths(case, env: Env, tmp: Path) -> dict:
    """Placeholders of this case: copies of the good files it names, its own output folder."""
    paths = {"tmp": str(tmp), "out": str(tmp / "out"), "body": str(env.body[".obj"])}
    (tmp / "out").mkdir()
    text = " ".join(case.args)
    inputs = tmp / "in"
    inputs.mkdir()
    for name in ("model", "mapped"):
        if "{" + name + "}" in text:
            good = getattr(env, name)
            paths[name] = str(shutil.copy(good, inputs / good.name))
    if "{db}" in text:
        paths["db"] = str(shutil.copytree(env.db, inputs / "db"))
    if case.setup is not None:
        paths.update(case.setup(env, tmp))
    return paths


def _outfile(args: list[str]) -> str | None:
    for flag in ("--out", "-o"):
        if flag in args:
            return args[args.index(flag) + 1]
    return None


@contextmanager
def _working_directory(path: Path):
    """Run in ``path``: a command told to write to '.' writes there, not into the source tree."""
    previous = os.getcwd()
    os.chdir(path)
    try:
        yield
    finally:
        os.chdir(previous)


def run_case(case, env: Env, tmp: Path, seconds: int = CASE_SECONDS) -> str | None:
    """None if the door behaved; otherwise what went wrong, in one paragraph."""
    try:
        return _run_case(case, env, tmp, seconds)
    except CaseTimeout as exc:
        return f"hangs or does unbounded work: {exc}"


def _run_case(case, env: Env, tmp: Path, seconds: int) -> str | None:
    paths = _paths(case, env, tmp)
    with warnings.catch_warnings(record=True) as caught, _time_limit(seconds), _working_directory(tmp / "out"):
        warnings.simplefilter("always")
        warnings.filterwarnings("ignore", category=DeprecationWarning)  # library internals, not the user's view
        warnings.filterwarnings("ignore", category=PendingDeprecationWarning)
        if case.call is not None:
            try:
                outcome = case.call(env, paths)
            except BodyspaceError as exc:
                if not str(exc).strip():
                    return f"refused with an empty {type(exc).__name__} message"
                outcome, refused, message = None, True, str(exc)
            except Exception as exc:  # noqa: BLE001 - any other exception is the traceback we look for
                return f"traceback: {type(exc).__name__}: {exc}"
            else:
                refused = False
        else:
            args = [a.format(**paths) for a in case.args]
            paths["outfile"] = _outfile(args)
            outcome = runner.invoke(app, args)
            message = outcome.output
            if outcome.exception is not None and not isinstance(outcome.exception, SystemExit):
                return f"traceback: {type(outcome.exception).__name__}: {outcome.exception}"
            if "Traceback" in outcome.output:
                return "traceback in the output: " + outcome.output[-400:]
            refused = outcome.exit_code != 0
            if refused and not outcome.output.strip():
                return f"exit {outcome.exit_code} without a message"
            if outcome.exit_code == EXIT_INTERNAL_ERROR:  # the error exit's "this is a bug" line
                return "internal error (exit 3): " + outcome.output[-400:]
    # ResourceWarning is hidden by Python's default filters (and fires at garbage collection, so in
    # whichever case runs then): not something the user sees.
    raw = [w for w in caught if not issubclass(w.category, (DeprecationWarning, PendingDeprecationWarning,
                                                            ResourceWarning))]
    if raw:
        w = raw[0]
        return f"raw Python warning reaches the user: {w.category.__name__}: {w.message} ({Path(w.filename).name})"
    if refused:
        if case.refusal is not None:
            try:
                case.refusal(env, paths, message)
            except AssertionError as exc:
                return f"refused, but not as it must be: {exc}"
        return None
    if case.accept is None:
        shown = outcome.output[-300:] if case.call is None else repr(outcome)[:300]
        return f"accepted a bad input (exit 0 / returned): {shown}"
    try:
        case.accept(env, paths, outcome)
    except AssertionError as exc:
        return f"exit 0 with a wrong result: {exc}"
    except BodyspaceError as exc:
        return f"exit 0 but the output does not read back: {exc}"
    return None


def _params():
    for case in CASES:
        reason = KNOWN_FAILURES.get(case.id)
        marks = [pytest.mark.xfail(strict=True, reason=reason)] if reason else []
        yield pytest.param(case, id=case.id, marks=marks)


@pytest.mark.parametrize("case", list(_params()))
def test_bad_input(case, env, tmp_path):
    problem = run_case(case, env, tmp_path, KNOWN_FAILURE_SECONDS if case.id in KNOWN_FAILURES else CASE_SECONDS)
    assert problem is None, f"{case.id} ({case.door}): {problem}"


# The counts are in the test id, so they show in every report (also under pytest-xdist, which
# hides a worker's prints): "test_catalogue_size_and_doors[576-bad-inputs-92-known-failures]".
@pytest.mark.parametrize("counts", [f"{len(CASES)}-bad-inputs-{len(KNOWN_FAILURES)}-known-failures"])
def test_catalogue_size_and_doors(counts, capsys):
    """At least 200 distinct bad inputs, and every command and library door is among them."""
    # Each id is one generated input at one door (many CLI cases share their argument list and
    # differ in the file their setup writes), so the ids count the distinct inputs.
    distinct = {case.id for case in CASES}
    doors = {case.door for case in CASES}
    expected = {"assets", "population", "build", "sample", "measure", "generate", "morph", "crowd", "evaluate",
                "mapping fit", "mapping evaluate", "mapping shape", "demo", "rig", "BodyModel.load", "ScanDatabase.load",
                "ScanDatabase.from_meshes", "load_mesh", "load_measurement_set", "load_landmarks"}
    with capsys.disabled():
        print(f"\nfuzz: {len(CASES)} bad inputs at {len(doors)} doors; {len(KNOWN_FAILURES)} known failures "
              f"marked xfail for other areas")
    assert len(distinct) == len(CASES) >= MIN_DISTINCT_INPUTS
    assert expected <= doors, sorted(expected - doors)
    assert set(KNOWN_FAILURES) <= {case.id for case in CASES}, "a known failure names no case"
