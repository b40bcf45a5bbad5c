"""The ``bodyspace`` command: a thin layer over the API (no algorithm lives here).

One module per command group (assets, population, examples (example-scans), data (import), model, measure,
semantics, mapping, demo, export (rig), motion, animate, register (register, landmarks));
``common`` holds what they share: the one error exit (``guarded``, wrapped around every command
here), the progress helper and the output policy.
"""

from __future__ import annotations

import typer

from bodyspace import __version__
from bodyspace.cli.animate import animate
from bodyspace.cli.assets import assets
from bodyspace.cli.common import guarded, out_console
from bodyspace.cli.data import import_meshes
from bodyspace.cli.demo import demo
from bodyspace.cli.examples import example_scans
from bodyspace.cli.export import rig
from bodyspace.cli.mapping import mapping_evaluate, mapping_fit, mapping_shape
from bodyspace.cli.measure import measure
from bodyspace.cli.model import build, sample
from bodyspace.cli.motion import motion_info, motion_match
from bodyspace.cli.population import population
from bodyspace.cli.register import landmarks, register
from bodyspace.cli.semantics import crowd, evaluate, generate, morph

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Statistical human body models: assets, synthetic scan databases, pictures.")


def _print_version(value: bool) -> None:
    if value:
        out_console.print(f"bodyspace {__version__}", highlight=False)
        raise typer.Exit()


@app.callback()
def _main(version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True,
                                       help="Print the version and exit.")):
    """Statistical human body models: assets, synthetic scan databases, pictures."""


for _name, _command in (("assets", assets), ("population", population), ("example-scans", example_scans),
                        ("demo", demo), ("import", import_meshes),
                        ("build", build),
                        ("sample", sample), ("measure", measure), ("evaluate", evaluate),
                        ("generate", generate), ("morph", morph), ("crowd", crowd), ("rig", rig),
                        ("animate", animate), ("register", register), ("landmarks", landmarks)):
    app.command(_name)(guarded(_command))
mapping_app = typer.Typer(no_args_is_help=True, help="Measurements → shape: forest with linear leaves, exact refinement.")
for _name, _command in (("fit", mapping_fit), ("shape", mapping_shape), ("evaluate", mapping_evaluate)):
    mapping_app.command(_name)(guarded(_command))
app.add_typer(mapping_app, name="mapping")
motion_app = typer.Typer(no_args_is_help=True, help="Motion capture (BVH): inspect a clip, match its skeleton to a rig.")
for _name, _command in (("info", motion_info), ("match", motion_match)):
    motion_app.command(_name)(guarded(_command))
app.add_typer(motion_app, name="motion")


def main() -> None:  # pragma: no cover - console entry point
    app(prog_name="bodyspace")
