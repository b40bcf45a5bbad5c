"""``bodyspace sample``: random bodies from a BodyModel file (meshes and a contact sheet);
``bodyspace build`` is in ``cli.build``."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np
import typer

from bodyspace.cli.common import (
    MESH_SUFFIXES,
    SAMPLE_CHUNK,
    SHEET_MAX,
    ForceOption,
    SeedOption,
    check_choice,
    check_folder_output,
    out_console,
    output_folder,
    progress,
)
from bodyspace.cli.resources import check_bodies_fit
from bodyspace.errors import ParameterError
from bodyspace.mesh.io import save_mesh
from bodyspace.model import BodyModel
from bodyspace.report.render import contact_sheet

SAMPLES_KIND = "samples"
# The widest truncation --sigma takes: beyond 10 SD a Gaussian shape space gives no body
# (and inf would be an untruncated draw, not a truncation).
SIGMA_MAX = 10.0


def sample(model_file: Path = typer.Argument(..., help="Model file (.npz, bodyspace build)."),
           n: int = typer.Option(10, "-n", "--number", min=1, help="Number of bodies."),
           out: Path = typer.Option(..., "--out", help="Output folder (must not exist, see --force)."),
           components: Optional[int] = typer.Option(None, "--components", min=1,
                                                    help="Leading components that vary (default all)."),
           sigma: float = typer.Option(2.0, "--sigma", min=0.01, max=SIGMA_MAX,
                                       help="Truncation of each coefficient, in standard deviations "
                                            f"(0.01 to {SIGMA_MAX:g})."),
           fmt: str = typer.Option("obj", "--format", help="Mesh format: obj, ply or glb (metres)."),
           seed: int = SeedOption(),
           png: bool = typer.Option(True, "--png/--no-png", help="Also write a contact sheet samples.png "
                                                                 f"(of the first {SHEET_MAX} bodies)."),
           force: bool = ForceOption):
    """Sample random bodies from a model: meshes (metres) and a PNG contact sheet."""
    # Decoded and written SAMPLE_CHUNK at a time, so any -n fits in memory; the bodies are those
    # of BodyModel.sample(n, ...) (one coefficient draw, then decoding row by row).
    fmt = check_choice(fmt, "--format", tuple(s[1:] for s in MESH_SUFFIXES))
    model = BodyModel.load(model_file)
    if components is not None and components > model.n_components:
        raise ParameterError(f"--components {components}: {model_file} has {model.n_components} components; "
                             f"expected at most {model.n_components}")
    check_folder_output(out, "--out", force, SAMPLES_KIND)  # a bad --out is said first
    check_bodies_fit(n, fmt, model.n_components, len(model.template_vertices), len(model.faces), out)
    names = [f"body_{i:0{max(3, len(str(n - 1)))}d}.{fmt}" for i in range(n)]
    with output_folder(out, "--out", force, SAMPLES_KIND) as tmp, progress("sample") as cb:
        coefficients = model.sample_coefficients(n, n_components=components, sigma_range=sigma, rng=seed)
        sheet = []
        for start in range(0, n, SAMPLE_CHUNK):
            bodies = model.reconstruct(coefficients[start:start + SAMPLE_CHUNK])
            for i, body in enumerate(bodies, start):
                save_mesh(tmp / names[i], body, model.faces)
                if i < SHEET_MAX:
                    sheet.append(body)
            cb(f"wrote {names[min(n, start + SAMPLE_CHUNK) - 1]}", 0.9 * min(n, start + SAMPLE_CHUNK) / n)
        if png:
            cb("rendering samples.png", 0.9)
            shown = f"the first {len(sheet)} of {n}" if n > len(sheet) else f"{n}"
            contact_sheet(np.asarray(sheet), model.faces, tmp / "samples.png", labels=names[:len(sheet)],
                          title=f"{shown} samples, {components or model.n_components} components, "
                                f"within {sigma:g} SD")
        cb("done", 1.0)
    out_console.print(f"wrote {n} bodies to {out}" + (" and samples.png" if png else "")
                      + (f" (the sheet shows the first {SHEET_MAX})" if png and n > SHEET_MAX else ""))

