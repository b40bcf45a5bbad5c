"""``bodyspace demo``: the main job end to end on the default data, into one new folder."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from bodyspace.cli.common import (
    AssetsOption,
    ForceOption,
    SeedOption,
    check_folder_output,
    out_console,
    progress,
)
from bodyspace.cli.population import check_poses
from bodyspace.report.demo import DEMO_KIND, run_demo


def demo(out: Path = typer.Option(Path("bodyspace-demo"), "--out",
                                  help="Output folder (must not exist, see --force)."),
         subjects: int = typer.Option(24, "--subjects", min=2, help="Number of synthetic subjects."),
         poses: int = typer.Option(5, "--poses", min=0, help="Poses per subject besides the rest pose "
                                                             "(at most the library's 38)."),
         seed: int = SeedOption(),
         force: bool = ForceOption,
         assets: Optional[Path] = AssetsOption):
    """The main job end to end on the default data: assets, population, pictures, summary.

    The folder appears complete or not at all (built under a temporary name, then renamed)."""
    check_folder_output(out, "--out", force, DEMO_KIND)
    check_poses(poses)
    with progress("demo") as cb:
        summary = run_demo(out, subjects=subjects, poses=poses, rng=seed, assets_root=assets, progress=cb,
                           overwrite=force, flag="--force")
    table = Table(title="population vs. survey (mean ± SD)")
    for col in ("sex", "n", "stature cm", "target", "BMI kg/m²", "target", "mass kg"):
        table.add_column(col)
    for sex, row in summary["population"].items():
        s, b, m = row["stature_cm"], row["bmi_kg_m2"], row["mass_kg"]
        table.add_row(sex, str(row["subjects"]), f"{s['mean']:.1f} ± {s['sd']:.1f}",
                      f"{s['target_mean']:.1f} ± {s['target_sd']:.1f}", f"{b['mean']:.2f} ± {b['sd']:.2f}",
                      f"{b['target_mean']:.2f} ± {b['target_sd']:.2f}", f"{m['mean']:.1f} ± {m['sd']:.1f}")
    out_console.print(table)
    out_console.print(f"wrote {summary['output']}: " + ", ".join(summary["pictures"] + ["summary.json", "population/"]))
    out_console.print(f"timings (s): {json.dumps(summary['timings_s'])}")
