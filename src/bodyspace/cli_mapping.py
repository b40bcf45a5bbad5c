"""``bodyspace mapping evaluate``: Tables 1-2 and Figures 4 and 6 of Rupprecht et al. for a model."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from bodyspace.errors import BodyspaceError


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
    from rich.markup import escape
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
    from rich.table import Table

    from bodyspace.mapping.evaluate import (decode_seconds, default_sizes, estimate_seconds, evaluate_mapping,
                                            write_report)
    from bodyspace.model import BodyModel

    console = Console()
    try:
        body_model = BodyModel.load(model)
        d_samples, d_held = default_sizes(body_model)
        samples = d_samples if samples is None else samples
        held_out = d_held if held_out is None else held_out
        if body_model.encoding != "vertex":
            per_body = decode_seconds(body_model)
            eta = estimate_seconds(body_model, samples, held_out, per_body, sweep=sweep)
            console.print(f"RRE model: every body is decoded ({1000 * per_body:.0f} ms each, measured); "
                          f"{samples} training + {held_out} held-out bodies, predictions and refinement: "
                          f"about {_duration(eta)} (--samples / --held-out make it shorter)", highlight=False)
        with Progress(TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.percentage:>3.0f}%"),
                      TimeElapsedColumn(), TextColumn("eta"), TimeRemainingColumn(),
                      TextColumn("{task.fields[message]}"), console=console) as bar:
            task = bar.add_task("mapping evaluate", total=1.0, message="")
            ev, _ = evaluate_mapping(body_model, samples, held_out, seed, n_trees=trees, sweep=sweep,
                                     progress=lambda msg, frac: bar.update(task, completed=frac, message=msg))
        files = write_report(body_model, ev, out)
    except BodyspaceError as exc:
        console.print(f"[red]error:[/red] {escape(str(exc))}", soft_wrap=True, highlight=False)
        raise typer.Exit(code=2)
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
