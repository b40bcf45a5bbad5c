"""``bodyspace example-scans``: a folder of registered scans as a user would bring them (another
topology, posed, off the origin, in mm, a labels CSV and a landmark file), made from the CC0
assets (``synth.foreign.write_scan_folder``), to try ``import``, ``build --landmarks`` and the
commands on a model of another topology."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from bodyspace.cli.common import (
    AssetsOption,
    ForceOption,
    SeedOption,
    check_choice,
    check_folder_output,
    console,
    out_console,
    progress,
)
from bodyspace.cli.resources import check_disk
from bodyspace.data.template import load_template
from bodyspace.synth.foreign import FOLDER_UNITS, SCAN_FOLDER_KIND, SESSION_POSES, write_scan_folder
from bodyspace.synth.phenotype import PhenotypeModel

# Bytes an OBJ line of a vertex or face takes at most (mm coordinates with 6 decimals).
OBJ_LINE_BYTES = 48


def example_scans(out: Path = typer.Option(..., "--out", help="Folder to write (must not exist, see --force)."),
                  subjects: int = typer.Option(10, "--subjects", min=1, max=500, help="Number of subjects (1-500)."),
                  poses: int = typer.Option(2, "--poses", min=0, max=len(SESSION_POSES),
                                            help="Poses per subject besides the A-pose: the first of "
                                                 f"{', '.join(SESSION_POSES)}."),
                  vertices: int = typer.Option(5000, "--vertices", min=2000, max=30000,
                                               help="Vertices of the remeshed topology (2,000-30,000)."),
                  units: str = typer.Option("mm", "--units", help="Length unit of the mesh files: m, cm or mm."),
                  rest_name: str = typer.Option("a_pose", "--rest-name", help="Pose name of the A-pose scans in "
                                                                            "labels.csv."),
                  seed: int = SeedOption(),
                  force: bool = ForceOption,
                  assets: Optional[Path] = AssetsOption):
    """Write example scans of another topology: OBJ meshes (posed, off the origin, floor not at zero),
    labels.csv (stature_cm, mass_kg, sex, age_years) and landmarks.json."""
    units = check_choice(units, "--units", tuple(FOLDER_UNITS))
    check_folder_output(out, "--out", force, SCAN_FOLDER_KIND)
    template = load_template(assets)
    n_meshes = subjects * (1 + poses)
    check_disk(n_meshes * 3 * vertices * OBJ_LINE_BYTES, out, f"--subjects {subjects} --poses {poses} "
               f"--vertices {vertices}", "ask for fewer subjects, poses or vertices")
    with progress("example-scans") as cb:
        folder = write_scan_folder(template, PhenotypeModel(template), out, subjects, poses, target_vertices=vertices,
                                   units=units, rest_name=rest_name, rng=seed, overwrite=force, progress=cb)
    out_console.print(f"wrote {out}: {len(folder.meshes)} scans ({subjects} subjects x {', '.join(folder.poses)}) of "
                      f"one topology of {folder.topology.n_vertices} vertices in {units}, {folder.labels_csv.name}, "
                      f"{folder.landmarks_json.name}", highlight=False, soft_wrap=True)
    console.print(f"next: bodyspace import {out} --labels {folder.labels_csv} --units {units} --rest-pose {rest_name} "
                  f"--landmarks {folder.landmarks_json} --out DB", highlight=False, soft_wrap=True)
