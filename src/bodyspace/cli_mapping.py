"""``bodyspace mapping evaluate``: Tables 1-2 and Figures 4 and 6 of Rupprecht et al. for a model."""

from __future__ import annotations

from pathlib import Path

import typer

from bodyspace.errors import BodyspaceError


def mapping_evaluate(model: Path = typer.Argument(..., help="A BodyModel file (.npz) with the vertex encoding."),
                     out: Path = typer.Option(Path("mapping_report"), "--out", "-o", help="Output folder."),
                     samples: int = typer.Option(10000, help="Training bodies (Sec. 4.1: 10,000)."),
                     held_out: int = typer.Option(1000, help="Held-out feasible requests."),
                     seed: int = typer.Option(0, help="Seed of the training set (held-out: seed + 1) and forest.")):
    """Linear vs forest vs forest + exact refinement: measured − requested (cm) per parameter,
    a Figure-4-like PNG and the shoulder-size sweep of Figure 6."""
    from rich.console import Console
    from rich.markup import escape
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
    from rich.table import Table

    from bodyspace.mapping.evaluate import evaluate_mapping, write_report
    from bodyspace.model import BodyModel

    console = Console()
    try:
        body_model = BodyModel.load(model)
        with Progress(TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.percentage:>3.0f}%"),
                      TimeElapsedColumn(), TextColumn("{task.fields[message]}"), console=console) as bar:
            task = bar.add_task("mapping evaluate", total=1.0, message="")
            ev, _ = evaluate_mapping(body_model, samples, held_out, seed,
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
    console.print(f"refinement: {ev.timings['refine_ms_per_request']:.2f} ms per request; "
                  f"training set: {ev.timings['training_set_s']:.2f} s")
    for f in files.values():
        console.print(f"wrote {f}", soft_wrap=True, highlight=False)
