"""``bodyspace population``: a synthetic scan database folder."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from bodyspace.cli.common import (
    AssetsOption,
    ForceOption,
    SeedOption,
    check_folder_output,
    console,
    progress,
)
from bodyspace.cli.resources import check_disk, check_memory
from bodyspace.data.database import DATABASE_KIND
from bodyspace.data.template import load_template
from bodyspace.errors import ParameterError
from bodyspace.synth.population import REST_POSE, build_population, resolve_pose_set
from bodyspace.synth.poses import load_pose_library


def check_poses(poses: int, flag: str = "--poses") -> None:
    """Refuse more poses per subject than the pose library holds besides the rest pose."""
    available = sum(1 for name in load_pose_library().names if name != REST_POSE)
    if poses > available:
        raise ParameterError(f"{flag} {poses}: the pose library has {available} poses besides the rest pose; "
                             f"expected at most {flag} {available}")


# Bytes of memory a subject's draw takes before its scans are written (phenotype parameters,
# survey labels, ids and table rows), at least.
SUBJECT_BYTES = 512


def check_population_size(subjects: int, poses: int, n_vertices: int, out: Path) -> None:
    """Refuse a --subjects/--poses request whose subjects do not fit in memory or whose scans
    (float32 vertices) do not fit on the disk, before any work."""
    request = f"--subjects {subjects} --poses {poses}"
    fix = "ask for fewer subjects (--subjects) or poses (--poses)"
    check_memory(subjects * SUBJECT_BYTES, request, fix)
    check_disk(subjects * (1 + poses) * n_vertices * 3 * 4, out, request, fix)


def population(out: Path = typer.Option(..., "--out", help="Database folder to write (must not exist, see --force)."),
               subjects: int = typer.Option(20, "--subjects", min=1, help="Number of subjects."),
               poses: Optional[int] = typer.Option(None, "--poses", min=0,
                                                   help="Poses per subject besides the rest pose, drawn at random "
                                                        "per subject (at most the library's 38; default 5)."),
               pose_set: Optional[str] = typer.Option(None, "--pose-set",
                                                      help="Every subject in the same poses instead of random ones: "
                                                           "'standard' (8 poses spanning the library: arms up, "
                                                           "forward, crossed, behind the head, squat, step, bend, "
                                                           "twist) or pose names separated by commas (after the "
                                                           "rest pose, in that order)."),
               seed: int = SeedOption(),
               workers: Optional[int] = typer.Option(None, "--workers", min=1,
                                                     help="Processes making subjects side by side (default: one "
                                                          "per core). The database is the same for any number."),
               force: bool = ForceOption,
               assets: Optional[Path] = AssetsOption):
    """Build a synthetic scan database: survey-drawn adults in a rest pose plus POSES poses each
    (or the poses of --pose-set, the same for every subject)."""
    check_folder_output(out, "--out", force, DATABASE_KIND)
    if pose_set is not None:
        names = resolve_pose_set(pose_set, load_pose_library().names, flag="--pose-set")
        if poses is not None and poses != len(names):
            raise ParameterError(f"--poses {poses} with --pose-set {pose_set!r} ({len(names)} poses: "
                                 f"{', '.join(names)}); expected --poses {len(names)} or no --poses")
        pose_set, poses = names, len(names)
    elif poses is None:
        poses = 5
    check_poses(poses)
    template = load_template(assets)
    check_population_size(subjects, poses, len(template.vertices), out)
    with progress("population", eta=True) as cb:
        db = build_population(template, out, subjects, poses, rng=seed, overwrite=force, progress=cb, workers=workers,
                              pose_set=pose_set,
                              log=lambda line: console.print(line, highlight=False, soft_wrap=True))
    console.print(f"wrote {db!r} to {out}")
