"""``bodyspace measure``: measure meshes with the default (or a landmark-file) measurement set."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import Optional

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from bodyspace.cli.common import ForceOption, check_file_output
from bodyspace.errors import BodyspaceError
from bodyspace.measure import (
    evaluate,
    load_landmarks,
    load_measurement_set,
    to_json,
    with_landmarks,
)
from bodyspace.mesh.io import load_mesh
from bodyspace.report.render import contact_sheet


def measure(meshes: list[Path] = typer.Argument(..., help="Mesh files (OBJ/PLY/GLB), metres, +Y up."),
            landmarks: Optional[Path] = typer.Option(None, "--landmarks", help="Landmark file for another topology "
                                                     "(JSON {\"landmarks\": {name: vertex id or {\"vertices\": [...], \"weights\": [...]}}}, "
                                                     "at most 25 names; docs/measurements.md)."),
            json_out: bool = typer.Option(False, "--json", help="Print JSON: name → {value, unit}."),
            csv_out: bool = typer.Option(False, "--csv", help="Print CSV: mesh,name,value,unit."),
            png: Optional[Path] = typer.Option(None, "--png", help="Draw the measured lines (front and side) to a PNG."),
            force: bool = ForceOption):
    """Measure body meshes: ISO 8559-1 girths and lengths, Rupprecht's six, volume, mass, BMI."""
    if png is not None:
        check_file_output(png, "--png", force, (".png",), example="measurements.png")
    try:
        mset = load_measurement_set()
        if landmarks is not None:
            lms, nv = load_landmarks(landmarks)
            mset = with_landmarks(mset, lms, nv, str(landmarks))
        results, bodies = {}, []
        for path in meshes:
            v, f = load_mesh(path)
            results[str(path)] = evaluate(mset, v, f, keep_polylines=png is not None)
            bodies.append((v, f))
        if png is not None:
            polys = [[m.polyline for m in r.values() if m.polyline is not None and not np.isnan(m.value)]
                     for r in results.values()]
            contact_sheet([b[0] for b in bodies], [b[1] for b in bodies], png, labels=[Path(p).name for p in results],
                          views=("front", "side"), polylines=polys, title="bodyspace measure", panel_height=6.0)
    except BodyspaceError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(code=2)
    if csv_out:
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow(["mesh", "name", "value", "unit"])
        for p, r in results.items():
            for name, e in to_json(r).items():
                w.writerow([p, name, "" if e["value"] is None else e["value"], e["unit"]])
        typer.echo(buf.getvalue().rstrip("\n"))
    elif json_out:
        out = {p: to_json(r) for p, r in results.items()}
        typer.echo(json.dumps(out[str(meshes[0])] if len(meshes) == 1 else out, indent=2))
    else:
        table = Table(title="measurements")
        table.add_column("name")
        for p in results:
            table.add_column(Path(p).name, justify="right")
        table.add_column("unit")
        rows = [to_json(r) for r in results.values()]
        for name, first in rows[0].items():
            cells = ["n/a" if row[name]["value"] is None else f"{row[name]['value']:.4g}" for row in rows]
            table.add_row(name, *cells, first["unit"])
        Console().print(table)
