"""The ``bodyspace`` command: a thin layer over the API (no algorithm lives here).

One module per command group (assets, population, examples (example-scans), data (import), build,
model (sample), measure, semantics, mapping, demo, export (rig), motion, animate, register (register,
landmarks));
``common`` holds what they share: the one error exit (``guarded``, wrapped around every command
here), the progress helper and the output policy.

Commands are loaded lazily (click's "lazily loading subcommands"; typer's groups are click's,
vendored): ``COMMANDS`` names each
command, its one-line help and the module that implements it, and only the module of the command
being run is imported. ``bodyspace --help`` reads the table alone; importing every command module
would import the whole library (scipy, matplotlib, numba, trimesh: ~2.5 s before anything runs).
A new command is a function in its module plus one entry in ``COMMANDS`` (tests/test_cli.py fails
until the entry's help is the first paragraph of the function's docstring).
"""

from __future__ import annotations

import importlib
from typing import NamedTuple

import typer
import typer.main
import typer.models
from typer.core import TyperCommand, TyperGroup

from bodyspace import __version__
from bodyspace.cli.common import guarded, out_console


class CommandEntry(NamedTuple):
    """Where a command lives: ``module``'s ``attribute`` is the command's function (wrapped in
    ``guarded`` here) or, for a group (``mapping``, ``motion``), its ``typer.Typer``. ``help`` is
    the first paragraph of the command's docstring (or the group's help), shown by ``bodyspace
    --help`` without importing the module; tests/test_cli.py checks it against the code."""
    module: str
    attribute: str
    help: str


# In the order of `bodyspace --help`.
COMMANDS: dict[str, CommandEntry] = {
    "assets": CommandEntry(
        "bodyspace.cli.assets", "assets",
        "Show where the CC0 MakeHuman assets are and whether they verify."),
    "population": CommandEntry(
        "bodyspace.cli.population", "population",
        "Build a synthetic scan database: survey-drawn adults in a rest pose plus POSES poses each\n"
        "(or the poses of --pose-set, the same for every subject)."),
    "example-scans": CommandEntry(
        "bodyspace.cli.examples", "example_scans",
        "Write example scans of another topology: OBJ meshes (posed, off the origin, floor not at zero),\n"
        "labels.csv (stature_cm, mass_kg, sex, age_years) and landmarks.json."),
    "demo": CommandEntry(
        "bodyspace.cli.demo", "demo",
        "The main job end to end on the default data: assets, population, pictures, summary."),
    "import": CommandEntry(
        "bodyspace.cli.data", "import_meshes",
        "Import a folder of your own registered meshes (or, with --register, raw scans) and a labels CSV as a scan\n"
        "database."),
    "build": CommandEntry(
        "bodyspace.cli.build", "build",
        "Build a BodyModel (template, encoder statistics, PCA shape space, measurement set) from a scan database."),
    "sample": CommandEntry(
        "bodyspace.cli.model", "sample",
        "Sample random bodies from a model: meshes (metres) and a PNG contact sheet."),
    "measure": CommandEntry(
        "bodyspace.cli.measure", "measure",
        "Measure body meshes: ISO 8559-1 girths and lengths, Rupprecht's six, volume, mass, BMI."),
    "evaluate": CommandEntry(
        "bodyspace.cli.semantics", "evaluate",
        "Hasler Table 1 (10-fold cross-validated RMSE per label and regressor) and Hasler Table 2 (angles between\n"
        "the non-linear model's morphing directions at every subject)."),
    "generate": CommandEntry(
        "bodyspace.cli.semantics", "generate",
        "A body that measures what is asked (labels such as stature, mass, sex within 4 mm / 0.5 kg, and any length of\n"
        "the measurement set, e.g. waist_size, shoulder_width, within 1 mm by exact refinement); the rest at random."),
    "morph": CommandEntry(
        "bodyspace.cli.semantics", "morph",
        'Change a body: --set stature=+5cm --keep mass ("taller, same weight"), optionally within a --mask.'),
    "crowd": CommandEntry(
        "bodyspace.cli.semantics", "crowd",
        "A crowd meeting the request (values or ranges), the rest random: meshes, a CSV of measurements, a PNG line-up."),
    "rig": CommandEntry(
        "bodyspace.cli.export", "rig",
        "A rigged glTF 2.0 of a body, bind pose = the mesh as given. Template topology: skeleton regressed from its\n"
        "vertices, MakeHuman's CC0 skin weights, optional morph targets of a model's semantic variables. Any other\n"
        "humanoid mesh: the rig embedded into it (the template fitted inside), bone-heat weights (4 per vertex), written\n"
        "in metres, +Y up, facing +Z."),
    "animate": CommandEntry(
        "bodyspace.cli.animate", "animate",
        "Put a motion capture clip on a body: retargeted (Rupprecht §3.3.3), feet kept still where the clip's feet are\n"
        "planted (two-bone IK), skinned; written as an animated rigged glTF, a BVH or a mesh sequence."),
    "register": CommandEntry(
        "bodyspace.cli.register", "register",
        "Fit the template to a raw scan: registered mesh, distances, pose, measurements, a PNG."),
    "landmarks": CommandEntry(
        "bodyspace.cli.register", "landmarks",
        "Landmarks for a mesh of another topology: register the template to it and carry them across."),
    "agreement": CommandEntry(
        "bodyspace.cli.agreement", "agreement",
        "A method's measurements against a reference's over a sample of subjects, as ISO 20685-1 evaluates\n"
        "them: per measurement the mean error, its 95 % confidence interval and whether it lies within the\n"
        "maximum allowable error."),
    "mapping": CommandEntry(
        "bodyspace.cli.mapping", "app",
        "Measurements → shape: forest with linear leaves, exact refinement."),
    "motion": CommandEntry(
        "bodyspace.cli.motion", "app",
        "Motion capture (BVH): inspect a clip, match its skeleton to a rig."),
}


def load_command(name: str, entry: CommandEntry, *, pretty_exceptions_short: bool = True,
                 rich_markup_mode=typer.core.DEFAULT_MARKUP_MODE) -> TyperCommand | TyperGroup:
    """The command ``name`` of ``entry``, built exactly as ``app.command(name)(guarded(fn))``
    (or ``app.add_typer(group)``) would build it. The module is resolved by name here, the one
    place that does so: importing it at the top is what lazy loading avoids."""
    target = getattr(importlib.import_module(entry.module), entry.attribute)
    if isinstance(target, typer.Typer):
        return typer.main.get_command(target)
    info = typer.models.CommandInfo(name=name, callback=guarded(target))
    return typer.main.get_command_from_info(info, pretty_exceptions_short=pretty_exceptions_short,
                                            rich_markup_mode=rich_markup_mode)


class LazyGroup(TyperGroup):
    """The top-level group: lists the commands of ``COMMANDS`` and imports a command's module only
    when that command is run (or its own ``--help`` is asked for).

    ``self.commands`` holds light stand-ins (name and help only) so that click and typer find the
    names (``No such command``, the "Did you mean" suggestion) and the help listing shows the help;
    ``get_command`` replaces a stand-in by the real command on first use."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.commands = {name: TyperCommand(name, help=entry.help) for name, entry in COMMANDS.items()}
        self._loaded: set[str] = set()
        self._listing = False

    def list_commands(self, ctx) -> list[str]:
        return list(COMMANDS)

    def get_command(self, ctx, cmd_name: str) -> TyperCommand | TyperGroup | None:
        if cmd_name not in COMMANDS:
            return None
        if not self._listing and cmd_name not in self._loaded:
            self.commands[cmd_name] = load_command(cmd_name, COMMANDS[cmd_name],
                                                   pretty_exceptions_short=app.pretty_exceptions_short,
                                                   rich_markup_mode=self.rich_markup_mode)
            self._loaded.add(cmd_name)
        return self.commands[cmd_name]

    def format_help(self, ctx, formatter) -> None:
        # The listing asks get_command for every command: answer it from the table (stand-ins
        # not yet loaded), not by importing every module.
        self._listing = True
        try:
            super().format_help(ctx, formatter)
        finally:
            self._listing = False


app = typer.Typer(cls=LazyGroup, add_completion=False, no_args_is_help=True,
                  help="Statistical human body models: assets, synthetic scan databases, pictures.")


def _print_version(value: bool) -> None:
    if value:
        out_console.print(f"bodyspace {__version__}", highlight=False)
        raise typer.Exit()


@app.callback()
def _main(version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True,
                                       help="Print the version and exit.")):
    """Statistical human body models: assets, synthetic scan databases, pictures."""


def main() -> None:  # pragma: no cover - console entry point
    app(prog_name="bodyspace")
