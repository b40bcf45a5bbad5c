"""``bodyspace mapping fit | shape | evaluate``: Rupprecht et al.'s measurements-to-shape mapping
stored in a model file, bodies from six measurements, and Tables 1-2 / Figures 4 and 6."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from bodyspace.errors import BodyspaceError


def _progress_bar(console):
    from rich.progress import (
        BarColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )
    return Progress(TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.percentage:>3.0f}%"),
                    TimeElapsedColumn(), TextColumn("eta"), TimeRemainingColumn(),
                    TextColumn("{task.fields[message]}"), console=console)


def _fail(console, exc) -> None:
    from rich.markup import escape
    console.print(f"[red]error:[/red] {escape(str(exc))}", soft_wrap=True, highlight=False)
    raise typer.Exit(code=2)


def mapping_fit(model: Path = typer.Argument(..., help="A BodyModel file (.npz), vertex or RRE encoding."),
                out: Optional[Path] = typer.Option(None, "--out", "-o",
                                                   help="Write the model with its mapping here (default: MODEL itself)."),
                samples: Optional[int] = typer.Option(None, help="Training bodies (default 10,000 vertex, 1,000 RRE)."),
                seed: int = typer.Option(0, help="Seed of the training set and the forest."),
                trees: int = typer.Option(50, help="Trees of the forest.")):
    """Fit the forest (and the linear baseline) from six measurements to shape, and store it in the model file."""
    from rich.console import Console

    from bodyspace.model import BodyModel

    console = Console()
    try:
        body_model = BodyModel.load(model)
        with _progress_bar(console) as bar:
            task = bar.add_task("mapping fit", total=1.0, message="")
            body_model.fit_mapping(samples, seed=seed, n_trees=trees,
                                   progress=lambda msg, frac: bar.update(task, completed=frac, message=msg))
        path = body_model.save(out or model)
    except BodyspaceError as exc:
        _fail(console, exc)
    m = body_model.mapping
    console.print(f"wrote {path}: mapping from {', '.join(m.names)} (cm) to {m.k} coefficients, "
                  f"{m.samples} training bodies", soft_wrap=True, highlight=False)


def mapping_shape(model: Path = typer.Argument(..., help="A BodyModel file with a mapping (bodyspace mapping fit)."),
                  assignments: List[str] = typer.Option(..., "--set", help="A measurement, e.g. height=175cm; "
                                                                           "every one of the mapping's six."),
                  out: Path = typer.Option(..., "--out", "-o", help="Mesh file (.obj, .ply, .glb)."),
                  refine_body: bool = typer.Option(True, "--refine/--no-refine",
                                                   help="Refine the forest's body until it measures the request.")):
    """A body from Rupprecht's six measurements: the forest's prediction, then exact refinement."""
    from rich.console import Console

    from bodyspace.mesh.io import save_mesh
    from bodyspace.model import BodyModel
    from bodyspace.units import UnitError, kind_of, parse_assignment

    console = Console()
    try:
        body_model = BodyModel.load(model)
        mapping = body_model.mapping
        if mapping is None:
            raise BodyspaceError(f"{model}: has no mapping; run `bodyspace mapping fit {model}` first")
        targets = {}
        for text in assignments:
            t = parse_assignment(text)
            if t.kind != "value" or kind_of(t.name) != "length":
                raise UnitError(f"--set {text}: expected a length value such as {t.name}=90cm")
            targets[t.name] = 100.0 * t.value
        result = mapping.shape(body_model, targets, refine_result=refine_body)
        save_mesh(out, body_model.reconstruct(result.coefficients)[0], body_model.faces)
    except BodyspaceError as exc:
        _fail(console, exc)
    for name, asked, got in zip(mapping.names, result.targets[0], result.measured[0]):
        console.print(f"{name:15s} asked {asked:7.2f} cm  measures {got:7.2f} cm", highlight=False)
    if result.misses and result.misses[0]:
        console.print("[yellow]missed:[/yellow] " + ", ".join(f"{k} by {v['difference']:+.2f} cm"
                                                               for k, v in result.misses[0].items()), highlight=False)
    console.print(f"wrote {out}", soft_wrap=True, highlight=False)


def mapping_evaluate(model: Path = typer.Argument(..., help="A BodyModel file (.npz), vertex or RRE encoding."),
                     out: Path = typer.Option(Path("mapping_report"), "--out", "-o", help="Output folder."),
                     samples: Optional[int] = typer.Option(
                         None, help="Training bodies (Sec. 4.1: 10,000; default 10,000 for vertex models, "
                                    "1,000 for RRE models, whose every body is decoded)."),
                     held_out: Optional[int] = typer.Option(
                         None, help="Held-out feasible requests (default 1,000 vertex, 100 RRE)."),
                     seed: int = typer.Option(0, help="Seed of the training set (held-out: seed + 1) and forest."),
                     trees: int = typer.Option(50, help="Trees of the forest."),
                     sweep: bool = typer.Option(True, help="The shoulder-size sweep of Figure 6 (5 more requests).")):
    """Linear vs forest vs forest + exact refinement: measured − requested (cm) per parameter,
    a Figure-4-like PNG and the shoulder-size sweep of Figure 6."""
    from rich.console import Console
    from rich.table import Table

    from bodyspace.mapping.evaluate import (
        decode_seconds,
        default_sizes,
        estimate_seconds,
        evaluate_mapping,
        write_report,
    )
    from bodyspace.model import BodyModel

    console = Console()
    try:
        body_model = BodyModel.load(model)
        d_samples, d_held = default_sizes(body_model)
        samples = d_samples if samples is None else samples
        held_out = d_held if held_out is None else held_out
        if not body_model.encoder.is_linear:
            per_body = decode_seconds(body_model)
            eta = estimate_seconds(body_model, samples, held_out, per_body, sweep=sweep)
            console.print(f"{body_model.encoding} model: every body is decoded ({1000 * per_body:.0f} ms each, measured); "
                          f"{samples} training + {held_out} held-out bodies, predictions and refinement: "
                          f"about {_duration(eta)} (--samples / --held-out make it shorter)", highlight=False)
        with _progress_bar(console) as bar:
            task = bar.add_task("mapping evaluate", total=1.0, message="")
            ev, _ = evaluate_mapping(body_model, samples, held_out, seed, n_trees=trees, sweep=sweep,
                                     progress=lambda msg, frac: bar.update(task, completed=frac, message=msg))
        files = write_report(body_model, ev, out)
    except BodyspaceError as exc:
        _fail(console, exc)
    table = Table(title=f"measured − requested (cm) over {held_out} held-out requests: mean / variance")
    table.add_column("parameter")
    for m in ev.errors:
        table.add_column(m, justify="right")
    tabs = {m: ev.table(m) for m in ev.errors}
    for n in ev.names:
        table.add_row(n, *(f"{tabs[m][n]['mean']:+.4f} / {tabs[m][n]['variance']:.4f}" for m in ev.errors))
    table.add_row("all within 1 mm", *(f"{100 * ev.within(m):.1f} %" for m in ev.errors))
    console.print(table)
    console.print(f"refinement: {ev.timings['refine_ms_per_request']:.2f} ms per request, "
                  f"{ev.settings['refine_iterations_mean']:.1f} iterations on average "
                  f"(max {ev.settings['refine_iterations_max']}), {ev.settings['refine_decodes']} bodies decoded; "
                  f"training set: {ev.timings['training_set_s']:.2f} s", highlight=False)
    for f in files.values():
        console.print(f"wrote {f}", soft_wrap=True, highlight=False)


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"
