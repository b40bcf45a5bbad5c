"""How long a ``bodyspace`` command takes to start (issue: a command starts in under 1 s).

Each case runs as a user runs it, ``python -m bodyspace ARGS`` in a fresh interpreter (best of
``--repeat`` wall-clock runs), against two baselines measured in the same process:

* ``python -c "import numpy"``: the floor of any command of a numpy library;
* the eager start-up the CLI had before lazy command loading: every command module imported,
  then the same ARGS (``python -c "import bodyspace.cli.<every module>; main()" ARGS``).

    PYTHONPATH=src python benchmarks/bench_startup.py [--repeat 5] [--only help,measure-help]

The machine's load average is printed: on the shared 2-core machine the wall times move with it,
the ratios much less.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import best_time  # noqa: E402

from bodyspace.cli import COMMANDS  # noqa: E402
from bodyspace.data.template import load_template  # noqa: E402
from bodyspace.mesh.io import save_mesh  # noqa: E402

SRC = str(Path(__file__).resolve().parents[1] / "src")
# The old dispatcher imported every command module before parsing the arguments.
EAGER = ("import sys\n" + "".join(f"import {m}\n" for m in sorted({e.module for e in COMMANDS.values()}))
         + "from bodyspace.cli import main\nsys.argv = ['bodyspace'] + sys.argv[1:]\nmain()\n")


def run_seconds(argv: list[str], repeat: int) -> float:
    """Best wall seconds of ``repeat`` runs of ``argv`` (it must exit 0)."""
    env = {**os.environ, "PYTHONPATH": SRC}

    def once():
        r = subprocess.run(argv, env=env, capture_output=True, text=True)
        if r.returncode != 0:
            raise SystemExit(f"{' '.join(argv)} exited {r.returncode}:\n{r.stderr[-2000:]}")
    return best_time(once, repeat=repeat)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--only", default="", help="Comma-separated case names (default: all).")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        body = Path(tmp) / "template.obj"
        t = load_template()
        save_mesh(body, t.vertices, t.faces)
        cases = {
            "help": ["--help"],
            "version": ["--version"],
            "measure-help": ["measure", "--help"],
            "motion-info-help": ["motion", "info", "--help"],
            "mapping-fit-help": ["mapping", "fit", "--help"],
            "measure-template-obj": ["measure", str(body)],
        }
        only = [c for c in args.only.split(",") if c] or list(cases)
        print(f"load average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} {os.getloadavg()[2]:.2f}; "
              f"best of {args.repeat} wall-clock runs, each a fresh interpreter")
        numpy_s = run_seconds([sys.executable, "-c", "import numpy"], args.repeat)
        print(f"python -c 'import numpy': {numpy_s:.2f} s")
        for name in only:
            argv = cases[name]
            lazy = run_seconds([sys.executable, "-m", "bodyspace", *argv], args.repeat)
            eager = run_seconds([sys.executable, "-c", EAGER, *argv], args.repeat)
            print(f"{name:22s} bodyspace {' '.join(argv[:3]) if name != 'measure-template-obj' else 'measure template.obj'}:"
                  f" {lazy:.2f} s (every module imported first: {eager:.2f} s), speed-up x{eager / lazy:.1f};"
                  f" {lazy / numpy_s:.1f}x the numpy start")
        print(f"load average at the end {os.getloadavg()[0]:.2f}; at {time.strftime('%H:%M UTC', time.gmtime())}")


if __name__ == "__main__":
    main()
