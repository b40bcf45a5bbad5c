"""The README runs top to bottom: every ```bash and ```python block, in order, in a fresh folder.

The set-up block (the ``pip install ...`` lines) is skipped, and so is ``bodyspace demo`` (about
a minute and 2 GB; ``tests/test_cli.py`` runs it on a small population). Every other bash
command runs through ``bash -e`` in one temporary folder with ``bodyspace`` on the PATH as
``python -m bodyspace`` of this source tree; the python blocks are executed in one namespace,
in the same folder, between the bash commands that surround them. A failure names the README
line, the command and its output.

Cost: 70 steps, about 340 CPU seconds (2026-12-03; 396 before the CLI loaded only the command
being run), of which the interpreter start-ups are 1.5-3 CPU s each; register, rig and animate
are the biggest steps. Deselect with
``--deselect tests/test_readme.py::test_readme_runs_top_to_bottom``.
"""

from __future__ import annotations

import os
import re
import resource
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
from test_bvh import MOCAP

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
# Commands the test does not run, and why (matched against the start of a command).
SKIPPED = {"pip install": "the set-up: the test runs from the source tree",
           "bodyspace demo": "the demo is tested by tests/test_cli.py"}
# Seconds one README command may take before the test calls it hung.
COMMAND_TIMEOUT_S = 300


@dataclass
class Step:
    """One thing to run: a bash command (continuation lines joined) or a whole python block."""

    kind: str       # "bash" or "python"
    line: int       # 1-based README line where it starts
    text: str


def readme_steps(text: str) -> list[Step]:
    """The README's ```bash commands and ```python blocks, in order, without the skipped ones."""
    steps, kind, start, block = [], None, 0, []
    for i, line in enumerate(text.splitlines(), start=1):
        fence = re.match(r"^```(\w*)\s*$", line)
        if fence and kind is None:
            kind, start, block = fence.group(1) or "text", i + 1, []
            continue
        if fence:
            if kind == "bash":
                steps += _bash_commands(block, start)
            elif kind == "python":
                steps.append(Step("python", start, "\n".join(block)))
            kind = None
            continue
        if kind is not None:
            block.append(line)
    assert kind is None, f"README.md: the code block opened at line {start - 1} is never closed"
    return [s for s in steps if not any(s.text.startswith(p) for p in SKIPPED)]


def _bash_commands(lines: list[str], first: int) -> list[Step]:
    out, pending, at = [], "", first
    for k, line in enumerate(lines):
        if not pending:
            at = first + k
            if not line.strip() or line.lstrip().startswith("#"):
                continue
        if line.rstrip().endswith("\\"):
            pending += line.strip()[:-1].strip() + " "
            continue
        out.append(Step("bash", at, pending + line.strip()))
        pending = ""
    return out


def _shim(folder: Path) -> dict:
    """Environment whose ``bodyspace`` is ``python -m bodyspace`` of this source tree."""
    bin_dir = folder / ".bin"
    bin_dir.mkdir()
    exe = bin_dir / "bodyspace"
    exe.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m bodyspace "$@"\n')
    exe.chmod(0o755)
    env = dict(os.environ)
    env["PATH"] = f"{bin_dir}{os.pathsep}{env.get('PATH', '')}"
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT / "src")] + [p for p in [env.get("PYTHONPATH")] if p])
    env["COLUMNS"] = "200"         # rich: long lines unwrapped in the failure report
    return env


def test_readme_steps_parse_the_blocks():
    """The parser finds commands and python blocks, joins continuation lines, skips the set-up."""
    text = ("x\n```bash\npip install -e .\n```\n```bash\n# a comment\nbodyspace a \\\n    --b c\n"
            "bodyspace demo --out d\n\nbodyspace e\n```\n```python\nx = 1\ny = x\n```\n")
    steps = readme_steps(text)
    assert [(s.kind, s.line, s.text) for s in steps] == [
        ("bash", 7, "bodyspace a --b c"), ("bash", 11, "bodyspace e"), ("python", 14, "x = 1\ny = x")]


def test_readme_runs_top_to_bottom(tmp_path, monkeypatch):
    steps = readme_steps(README.read_text())
    assert sum(s.kind == "bash" for s in steps) >= 20 and sum(s.kind == "python" for s in steps) >= 3
    env = _shim(tmp_path)
    # The motion section animates a shared CMU clip: linked in where it is (never copied into the
    # repository); without it those steps are left out.
    clip = MOCAP / "131_01.bvh"
    if clip.is_file():
        (tmp_path / clip.name).symlink_to(clip)
    else:
        steps = [s for s in steps if clip.name not in s.text]
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PYTHONPATH", env["PYTHONPATH"])
    namespace: dict = {"__name__": "__readme__"}
    timings = []
    for step in steps:
        t, cpu = time.perf_counter(), _cpu_seconds()
        if step.kind == "bash":
            try:
                run = subprocess.run(["bash", "-e", "-c", step.text], cwd=tmp_path, env=env, capture_output=True,
                                     text=True, timeout=COMMAND_TIMEOUT_S)
            except subprocess.TimeoutExpired as exc:
                pytest.fail(f"README.md line {step.line}: `{step.text}` still running after {exc.timeout} s")
            if run.returncode != 0:
                pytest.fail(f"README.md line {step.line}: `{step.text}` exited {run.returncode}\n"
                            f"--- stdout\n{run.stdout}\n--- stderr\n{run.stderr}", pytrace=False)
        else:
            # Blank lines in front keep the README's line numbers in a traceback.
            code = compile("\n" * (step.line - 1) + step.text, str(README), "exec")
            try:
                exec(code, namespace)
            except Exception as exc:          # any failure of a README block is the test's failure
                pytest.fail(f"README.md python block at line {step.line}: {type(exc).__name__}: {exc}", pytrace=True)
        timings.append((time.perf_counter() - t, _cpu_seconds() - cpu, step.line, step.text.splitlines()[0][:60]))
    slowest = sorted(timings, reverse=True)[:8]
    print(f"\nREADME: {len(steps)} steps, {sum(t[0] for t in timings):.0f} s wall, "
          f"{sum(t[1] for t in timings):.0f} s CPU; slowest:\n" + "\n".join(
              f"  line {n}: {w:.1f} s wall, {c:.1f} s CPU  {cmd}" for w, c, n, cmd in slowest))


def _cpu_seconds() -> float:
    """User + system CPU seconds of this process and its finished children (load-independent)."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime
