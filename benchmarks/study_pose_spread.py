"""Run the pose spread study (issue 12: every measurement over the 39 library poses, measured as
posed and after unposing) and print its Markdown table, headed by the date and the code it ran on.

Run: python benchmarks/study_pose_spread.py [subjects] [--out FILE]
(about a minute a subject on two loaded cores; ``--out`` writes the table to FILE as well).
"""

from __future__ import annotations

import datetime
import platform
import subprocess
import sys
import time
from pathlib import Path

from bodyspace.data.template import load_template
from bodyspace.report.pose_spread_report import pose_spread_markdown
from bodyspace.studies.pose_spread import pose_spread_study


def _code_version() -> str:
    """The commit the study ran on (and whether the tree had changes), or 'unknown'."""
    root = Path(__file__).resolve().parents[1]
    try:
        commit = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True,
                                text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--", "src"], capture_output=True,
                               text=True, check=True).stdout.strip()
        branch = subprocess.run(["git", "-C", str(root), "rev-parse", "--abbrev-ref", "HEAD"], capture_output=True,
                                text=True, check=True).stdout.strip()
        return f"{branch} {commit}" + (" + uncommitted changes in src/" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def split_out_option(argv: list[str]) -> tuple[list[str], Path | None]:
    """The arguments without ``--out FILE``, and FILE (None when not given)."""
    if "--out" not in argv:
        return argv, None
    i = argv.index("--out")
    return argv[:i] + argv[i + 2:], Path(argv[i + 1])


def main(argv: list[str]) -> None:
    argv, out = split_out_option(argv)
    subjects = int(argv[0]) if argv else 4
    t = time.perf_counter()
    result = pose_spread_study(load_template(), subjects, rng=0)
    elapsed = time.perf_counter() - t
    header = (f"Pose spread study, {datetime.date.today().isoformat()}, code {_code_version()}, "
              f"{platform.python_version()} on {platform.machine()}; study took {elapsed:.0f} s. "
              "Measured as posed: `measure.evaluate` on the posed mesh; unposed: `rig.unpose.unpose` then "
              "`measure.evaluate`.")
    text = pose_spread_markdown(result, header)
    print(text)
    if out is not None:
        out.write_text(text)


if __name__ == "__main__":
    main(sys.argv[1:])
