"""``bodyspace mapping fit | shape | evaluate``: Rupprecht et al.'s measurements-to-shape mapping
stored in a model file, bodies from any of the measurement set's lengths (met to 1 mm by the
exact refinement, or refused), and Rupprecht Tables 1-2 / Rupprecht Figures 4 and 6."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer
from rich.table import Table

from bodyspace.cli.common import (
    MESH_SUFFIXES,
    ForceOption,
    SeedOption,
    check_file_output,
    check_folder_output,
    console,
    fail,
    guarded,
    out_console,
    output_folder,
    progress,
)
from bodyspace.errors import BodyspaceError
from bodyspace.mapping.gradients import RUPPRECHT_SIX, SUBSTITUTES
from bodyspace.mapping.training import default_sizes
from bodyspace.mesh.io import save_mesh
from bodyspace.model import BodyModel
from bodyspace.report.mapping_report import format_error, parameter_label, write_mapping_report
from bodyspace.studies.mapping import (
    decode_seconds,
    estimate_seconds,
    evaluate_mapping,
    exact_by_construction_note,
)
from bodyspace.units import UnitError, kind_of, parse_assignment

MAPPING_REPORT_KIND = "mapping_report"


def _fail(console, exc) -> None:
    """The shared error exit (cli.common.fail); ``console`` is kept for the callers' signature."""
    fail(exc)


def mapping_fit(model: Path = typer.Argument(..., help="A BodyModel file (.npz), vertex or RRE encoding."),
                out: Optional[Path] = typer.Option(None, "--out", "-o",
                                                   help="Write the model with its mapping here (default: MODEL itself)."),
                samples: Optional[int] = typer.Option(None, min=10, help="Training bodies, at least 10 (the linear map has "
                                                                         "7 unknowns per coefficient; default 10,000 vertex, 1,000 RRE or "
                                                                         "another topology)."),
                seed: int = SeedOption("Seed of the training set and the forest (an integer >= 0)."),
                trees: int = typer.Option(50, min=1, help="Trees of the forest."),
                force: bool = ForceOption):
    """Fit the forest (and the linear baseline) from six measurements to shape, and store it in the model file.

    The six are Rupprecht's on the template; on another topology the ISO measurements that stand in
    for the template's loops (chest_girth for breast_size, ...), said in the output."""
    if out is not None and not (out.exists() and model.exists() and out.samefile(model)):
        check_file_output(out, "--out", force, (".npz",), example="model.npz")
    try:
        body_model = BodyModel.load(model)
        with progress("mapping fit", eta=True) as cb:
            body_model.fit_mapping(samples, rng=seed, n_trees=trees, progress=cb)
        path = body_model.save(out or model)
    except BodyspaceError as exc:
        _fail(console, exc)
    m = body_model.mapping
    console.print(f"wrote {path}: mapping from {', '.join(m.names)} (cm) to {m.k} coefficients, "
                  f"{m.samples} training bodies", soft_wrap=True, highlight=False)
    note = inputs_note(m.names)
    if note:
        console.print(note, soft_wrap=True, highlight=False)


def _check_in_set(text: str, name: str, mset) -> None:
    """Refuse a --set name the model's measurement set does not measure, with the stand-in of a
    template loop (waist_size -> waist_girth) when the set has one."""
    if name in mset.names:
        return
    sub = next((n for n in SUBSTITUTES.get(name, ()) if n in mset.names), None)
    lengths = [m["name"] for m in mset.measurements if m["unit"] == "m"]
    hint = (f"{name} is a vertex loop of the template, which this model's topology does not have; ask {sub} "
            f"instead (--set {sub}=...)" if sub else f"expected one of {', '.join(lengths)}")
    raise UnitError(f"--set {text}: {name} is not in the model's measurement set ({mset.source}); {hint}")


def inputs_note(names) -> str:
    """Which of Rupprecht's six the mapping's inputs stand in for (another topology), or ''."""
    stand_ins = {sub: orig for orig, subs in SUBSTITUTES.items() for sub in subs}
    pairs = [f"{n} for {stand_ins[n]}" for n in names if n in stand_ins and n not in RUPPRECHT_SIX]
    missing = [n for n in RUPPRECHT_SIX if n not in names and not any(s in names for s in SUBSTITUTES[n])]
    if not pairs and not missing:
        return ""
    return ("inputs: the model's measurement set has not all of Rupprecht's six (four are vertex loops of the "
            "template): " + ", ".join(pairs) + (f"; without {', '.join(missing)}" if missing else ""))


def mapping_shape(model: Path = typer.Argument(..., help="A BodyModel file with a mapping (bodyspace mapping fit)."),
                  assignments: List[str] = typer.Option(..., "--set", help="A length of the measurement set, e.g. "
                                                                           "height=175cm, waist_size=80cm, "
                                                                           "shoulder_width=38cm (any subset; the "
                                                                           "mapping's inputs not given are drawn "
                                                                           "from the population)."),
                  out: Path = typer.Option(..., "--out", "-o", help="Mesh file (.obj, .ply, .glb)."),
                  refine_body: bool = typer.Option(True, "--refine/--no-refine",
                                                   help="Refine the forest's body until it measures the request."),
                  accept_misses: bool = typer.Option(False, "--accept-misses",
                                                     help="Write the body even if it misses a request by more than "
                                                          "the refinement's tolerance (exit 0)."),
                  seed: int = SeedOption("Seed of the mapping's inputs drawn from the population (an integer >= 0)."),
                  force: bool = ForceOption):
    """A body that measures the given lengths to 1 mm: the forest's prediction (inputs not given
    drawn from the population given the others), then exact refinement.

    A body that misses a request by more than 1 mm is not written (exit 2) unless --accept-misses."""
    check_file_output(out, "--out", force, MESH_SUFFIXES, example="body.obj")
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
            if t.name in targets:
                raise UnitError(f"--set {t.name}: asked twice ({text!r} after an earlier value); give each name once")
            _check_in_set(text, t.name, body_model.measurement_set)
            targets[t.name] = 100.0 * t.value
        result = mapping.shape(body_model, targets, refine_result=refine_body, rng=seed)
        given = mapping.given_inputs(targets)
        drawn = {n: v for n, v in zip(mapping.names, mapping.inputs(body_model, targets, seed)[0])
                 if n not in given}
    except BodyspaceError as exc:
        _fail(console, exc)
    for name, asked, got in zip(result.names, result.targets[0], result.measured[0]):
        out_console.print(f"{name:15s} asked {asked:7.2f} cm  measures {got:7.2f} cm", highlight=False)
    if drawn:
        console.print("the forest's other inputs, drawn from the population given these: "
                      + ", ".join(f"{n} {v:.1f} cm" for n, v in drawn.items()), soft_wrap=True, highlight=False)
    missed = result.misses[0] if result.misses else {}
    if missed:
        console.print("[yellow]missed:[/yellow] " + ", ".join(f"{k} by {v['difference']:+.2f} cm"
                                                               for k, v in missed.items())
                      + " (tolerance 0.10 cm)", highlight=False)
        if not accept_misses:
            _fail(console, BodyspaceError(f"the body misses {len(missed)} of the requested measurements (above); "
                                          f"{out} not written; pass --accept-misses to write it anyway"))
    save_mesh(out, body_model.reconstruct(result.coefficients)[0], body_model.faces)
    console.print(f"wrote {out}", soft_wrap=True, highlight=False)


def mapping_evaluate(model: Path = typer.Argument(..., help="A BodyModel file (.npz), vertex or RRE encoding."),
                     out: Path = typer.Option(Path("mapping_report"), "--out", "-o",
                                              help="Output folder (must not exist, see --force)."),
                     samples: Optional[int] = typer.Option(
                         None, min=10, help="Training bodies, at least 10 (Rupprecht §4.1: 10,000; default 10,000 for vertex models, "
                                    "1,000 for RRE models, whose every body is decoded, and models of another topology, "
                                    "whose girths are sliced)."),
                     held_out: Optional[int] = typer.Option(
                         None, min=1, help="Held-out feasible requests (default 1,000 vertex, 100 RRE or another "
                                           "topology)."),
                     seed: int = SeedOption("Seed of the training set (held-out: seed + 1) and forest "
                                            "(an integer >= 0)."),
                     trees: int = typer.Option(50, min=1, help="Trees of the forest."),
                     sweep: bool = typer.Option(True, help="The shoulder-size sweep of Rupprecht Figure 6 (5 more requests)."),
                     force: bool = ForceOption):
    """Linear vs forest vs forest + exact refinement: measured − requested (cm) per parameter,
    a PNG like Rupprecht Figure 4 and the shoulder-size sweep of Rupprecht Figure 6."""
    check_folder_output(out, "--out", force, MAPPING_REPORT_KIND)
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
        with progress("mapping evaluate", eta=True) as cb:
            ev, _ = evaluate_mapping(body_model, samples, held_out, seed, n_trees=trees, sweep=sweep, progress=cb)
        with output_folder(out, "--out", force, MAPPING_REPORT_KIND) as folder:
            files = {k: out / Path(f).name for k, f in write_mapping_report(body_model, ev, folder).items()}
    except BodyspaceError as exc:
        _fail(console, exc)
    table = Table(title=f"measured − requested (cm) over {held_out} held-out requests: mean / variance")
    table.add_column("parameter")
    for m in ev.errors:
        table.add_column(m, justify="right")
    tabs = {m: ev.table(m) for m in ev.errors}
    for n in ev.names:
        table.add_row(parameter_label(ev, n), *(f"{format_error(tabs[m][n]['mean'])} / "
                                                 f"{format_error(tabs[m][n]['variance'], False)}" for m in ev.errors))
    table.add_row("all within 1 mm", *(f"{100 * ev.within(m):.1f} %" for m in ev.errors))
    out_console.print(table)
    for note in (exact_by_construction_note(ev), inputs_note(ev.names)):
        if note:
            console.print(note, soft_wrap=True, highlight=False)
    out_console.print(f"refinement: {ev.timings['refine_ms_per_request']:.2f} ms per request, "
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


# The ``bodyspace mapping`` group; the dispatcher (bodyspace.cli) loads it when ``mapping`` is run.
app = typer.Typer(name="mapping", add_completion=False, no_args_is_help=True,
                  help="Measurements → shape: forest with linear leaves, exact refinement.")
for _name, _command in (("fit", mapping_fit), ("shape", mapping_shape), ("evaluate", mapping_evaluate)):
    app.command(_name)(guarded(_command))
