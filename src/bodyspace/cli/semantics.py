"""``bodyspace evaluate | generate | morph | crowd``: semantic control from the command line.

Thin layer over ``bodyspace.semantics.model.SemanticModel``; register with
``app.command("evaluate")(evaluate)`` etc. Every command takes the model file; the semantic
regressors live inside it, fitted on first use from ``--database`` (the scan database the model
was built from) and saved into the model file (atomically). A ``MODEL.semantics.npz`` that
earlier versions wrote beside the model is read once and folded into the model file.
"""

from __future__ import annotations

import csv
import json
import warnings
from pathlib import Path
from typing import List, Optional

import numpy as np
import typer
from rich.markup import escape
from rich.table import Table

from bodyspace.atomic import MARKDOWN_SIGNATURE, WRITTEN_BY, atomic_path
from bodyspace.cli.common import (
    MESH_SUFFIXES,
    SAMPLE_CHUNK,
    SHEET_MAX,
    ForceOption,
    SeedOption,
    check_file_output,
    check_folder_output,
    console,
    fail,
    out_console,
    output_folder,
    progress,
    report_warnings,
)
from bodyspace.cli.export import BonesOption, MorphsOption, PngOption, RigOption, check_rig_options, write_rigged
from bodyspace.cli.resources import check_bodies_fit
from bodyspace.data.database import ScanDatabase
from bodyspace.data.template import load_template
from bodyspace.errors import BodyspaceError, UnposeError
from bodyspace.mapping.gradients import SUBSTITUTES
from bodyspace.measure import evaluate as evaluate_measurements
from bodyspace.measure import to_json
from bodyspace.mesh.io import load_mesh, save_mesh
from bodyspace.model import BodyModel, request_tolerance
from bodyspace.register.detail import apply_detail, load_detail
from bodyspace.report.render import contact_sheet
from bodyspace.rig.posing import pose_bodies
from bodyspace.rig.unpose import fits_template, unpose
from bodyspace.semantics.evaluation import (
    RegressionTable,
    format_angle_table,
    format_rmse_table,
)
from bodyspace.semantics.labels import describe_source
from bodyspace.semantics.model import SemanticModel, semantics_path
from bodyspace.units import (
    ALIASES,
    UnitError,
    example,
    format_value,
    kind_of,
    parse_assignment,
)

CROWD_KIND = "crowd"

DatabaseOption = typer.Option(None, "--database", help="Scan database the model was built from: fits the semantic "
                                                       "regressors (saved into the model file).")
RefitOption = typer.Option(False, "--refit", help="With --database: fit again even if the model file holds "
                                                  "semantic regressors.")
ClampOption = typer.Option(False, "--clamp", help="Clamp requests outside the reachable range (with a warning) "
                                                  "instead of refusing them.")
SetOption = typer.Option(None, "--set", help="NAME=VALUE with units, e.g. stature=180cm, mass=80kg, sex=female, "
                                             "waist_size=80cm, thigh_girth_l=55cm (any length of the measurement "
                                             "set), stature=+5cm (morph), stature=155:185cm (a range).")
RangeOption = typer.Option(None, "--range", help="NAME=LOW:HIGH with units, e.g. stature=155:185cm.")
AcceptMissesOption = typer.Option(False, "--accept-misses", help="Write the body even if the exact refinement "
                                                                 "misses an asked length by more than 1 mm (a "
                                                                 "warning says by how much).")


# The shared error exit, progress bar and warning report (cli.common), under this module's names.
_fail, _progress, _report_warnings = fail, progress, report_warnings


def load_semantics(model_file: Path, database: Optional[Path], refit: bool, clamp: bool):
    """The model's ``SemanticModel``: stored in the model file; else fitted from ``database`` or
    folded in from a legacy ``MODEL.semantics.npz``, and then saved into the model file."""
    # refitting never reads the stored regressors, so damaged ones can be replaced
    model = BodyModel.load(model_file, semantics=not (refit and database is not None))
    sidecar = semantics_path(model_file)
    if database is not None and (refit or model.semantics is None):
        db = ScanDatabase.load(database)
        with _progress("fitting semantic regressors") as cb:
            cb("measuring the rest scans", 0.1)
            model.semantics = SemanticModel(model).fit(db)
            cb("done", 1.0)
        if _save_into(model, model_file):
            console.print(f"saved the semantic regressors into {model_file}", highlight=False)
    elif model.semantics is None and sidecar.is_file():
        model.semantics = SemanticModel.load(sidecar, model)
        if _save_into(model, model_file):
            console.print(f"note: folded {sidecar} into {model_file} (the semantic regressors now live in the "
                          f"model file; {sidecar.name} is left as it was and no longer read)", highlight=False)
    elif model.semantics is None:
        raise BodyspaceError(f"{model_file}: holds no semantic regressors; pass --database DB (the scan database "
                             "the model was built from) to fit them (saved into the model file)")
    return model.semantics.set_params(on_infeasible="clamp" if clamp else "raise")


def _save_into(model, model_file: Path) -> bool:
    """Save ``model`` (with its new semantic regressors) over ``model_file``, atomically; when
    that fails (read-only file or folder), say so and go on with the regressors in memory."""
    try:
        model.save(model_file)
    except OSError as exc:
        console.print(f"[yellow]warning:[/yellow] could not save the semantic regressors into {escape(str(model_file))} "
                      f"({escape(str(exc))}); they are used for this run only", soft_wrap=True, highlight=False)
        return False
    return True


def parse_targets(sets, ranges, allow_delta: bool, sm=None) -> dict:
    """Parse --set/--range; with the semantic model ``sm``, an unknown name is refused (with the
    accepted names) before its value is parsed. A name asked twice (two --set, or --set and
    --range) is refused: which one was meant?"""
    out = {}
    for text in list(sets or []) + list(ranges or []):
        name = str(text).partition("=")[0].strip()
        if sm is not None and "=" in str(text) and name:
            _check_stand_in(text, ALIASES.get(name, name), sm)
            sm.regressor(ALIASES.get(name, name))
        t = parse_assignment(text)
        if text in (ranges or []) and t.kind != "range":
            raise UnitError(f"--range {text!r}: expected NAME=LOW:HIGH, e.g. stature=155:185cm")
        if t.kind == "delta" and not allow_delta:
            raise UnitError(f"--set {text!r}: a change (+/-) needs a body to change; use a value, e.g. "
                            f"{t.name}={example(t.name)}, or bodyspace morph")
        if t.name in out:
            raise UnitError(f"--set/--range {t.name}: asked twice ({text!r} after an earlier value); "
                            f"give each name once")
        out[t.name] = t
    return out


def _check_stand_in(text: str, name: str, sm) -> None:
    """A template loop (waist_size, ...) asked of a model of another topology: name the ISO
    measurement that stands in for it there (``mapping.gradients.SUBSTITUTES``)."""
    if name in getattr(sm, "regressors_", {}) or name not in SUBSTITUTES:
        return
    sub = next((n for n in SUBSTITUTES[name] if n in getattr(sm, "regressors_", {})), None)
    if sub is not None:
        raise UnitError(f"--set {text}: {name} is a vertex loop of the template, which this model's topology does not "
                        f"have; ask {sub} instead (--set {sub}=...)")


def _result_table(title: str, result, sm) -> Table:
    table = Table(title=title)
    for col in ("variable", "asked", "reached", "off by", "tolerance"):
        table.add_column(col, justify="left" if col == "variable" else "right")
    for name, goal in result.targets.items():
        got = result.values[name]
        table.add_row(name, format_value(name, goal), format_value(name, got),
                      format_value(name, got - goal) if name != "sex" else f"{got - goal:+.3f}",
                      format_value(name, request_tolerance(sm, name)) if name != "sex" else "0.001")
    return table


def _save_mesh(path: Path, vertices, faces) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    save_mesh(path, vertices, faces)


# ----------------------------------------------------------------------------------- commands
def evaluate(model_file: Path = typer.Argument(..., help="Model file (.npz, bodyspace build)."),
             database: Optional[Path] = DatabaseOption, refit: bool = RefitOption,
             out: Optional[Path] = typer.Option(None, "--out", help="Markdown file for the tables "
                                                "(default MODEL.evaluation.md; a .json beside it)."),
             folds: Optional[int] = typer.Option(None, "--folds", min=2, help="Cross-validation folds (default 10, "
                                                  "or the number of subjects when fewer)."),
             seed: int = SeedOption("Fold shuffle seed (an integer >= 0)."),
             force: bool = ForceOption):
    """Hasler Table 1 (10-fold cross-validated RMSE per label and regressor) and Hasler Table 2 (angles between
    the non-linear model's morphing directions at every subject)."""
    out = out or model_file.with_name(model_file.name.removesuffix(".npz") + ".evaluation.md")
    check_file_output(out, "--out", force, (".md",), example="evaluation.md")
    check_file_output(out.with_suffix(".json"), "--out (its .json beside it)", force, (".json",))
    try:
        sm = load_semantics(model_file, database, refit, False)
        with _progress("evaluate") as cb:
            folds = min(10, len(sm.X_)) if folds is None else folds
            cb(f"{folds}-fold cross-validation of {len(sm.labels_)} labels x 3 regressors", 0.05)
            table1, table2 = sm.evaluate(folds=folds, rng=seed)
            cb("done", 1.0)
    except BodyspaceError as exc:
        _fail(exc)
    unit = {"length": "cm", "mass": "kg", "age": "years", "percent": "%"}
    scale = np.array([100.0 if kind_of(n) == "length" else 1.0 for n in table1.labels])
    names = [f"{n} ({unit.get(kind_of(n), '1')})" for n in table1.labels]
    shown = RegressionTable(table1.regressors, names, table1.rmse * scale, table1.n_samples, table1.folds)
    text1, text2 = format_rmse_table(shown), format_angle_table(table2)
    split = _split_text(table1, len(sm.X_))
    sources = _label_sources(sm)
    out_console.print(f"Labels: where their values came from\n" + "\n".join(f"  {line}" for line in sources) +
                      f"\n\nTable 1: RMSE, {split}\n{text1}\n\n"
                      f"Table 2: angles between non-linear morphing directions (degrees)\n{text2}",
                      highlight=False, soft_wrap=True)
    md = (f"{MARKDOWN_SIGNATURE}\n# Semantic regressors of {model_file.name}\n\n## Labels: where their values came "
          f"from\n\n" + "\n".join(f"- {line}" for line in sources) +
          f"\n\n## Table 1: RMSE ({split})\n\n{format_rmse_table(shown, markdown=True)}\n\n"
          f"## Table 2: angles between the non-linear model's morphing directions (degrees)\n\n"
          f"{format_angle_table(table2, markdown=True)}\n")
    with atomic_path(out) as tmp:
        tmp.write_text(md)
    payload = {"written_by": WRITTEN_BY,
               "labels": {"provenance": getattr(sm, "provenance_", {}), "skipped": getattr(sm, "skipped_", {}),
                          "unused_columns": getattr(sm, "unused_columns_", [])},
               "table1": {"regressors": table1.regressors, "labels": table1.labels, "rmse_si": table1.rmse.tolist(),
                          "n_samples": table1.n_samples.tolist(), "folds": table1.folds,
                          "label_folds": dict(zip(table1.labels, table1.label_folds.tolist()))},
               "table2": {k: {"mean_deg": m, "sd_deg": s} for k, (m, s) in table2.items()}}
    with atomic_path(out.with_suffix(".json")) as tmp:
        tmp.write_text(json.dumps(payload, indent=2))
    console.print(f"wrote {out} and {out.with_suffix('.json')}")


def _split_text(table: RegressionTable, n_subjects: int) -> str:
    """How Table 1 split the subjects: '10-fold cross-validation, 24 subjects once each', and
    the labels split otherwise (fewer known values: leave-one-out)."""
    text = f"{table.folds}-fold cross-validation, {n_subjects} subjects once each"
    if table.folds == n_subjects:
        text = f"leave-one-out cross-validation ({n_subjects} folds), {n_subjects} subjects once each"
    other = [f"{name} {k}-fold over its {n} known values" + (" (leave-one-out)" if k == n else "")
             for name, k, n in zip(table.labels, table.label_folds, table.n_samples) if k != table.folds]
    return text + (f"; {', '.join(other)}" if other else "")


def _label_sources(sm) -> list[str]:
    """One line per label saying where its values came from (``labels.describe_source``), then
    the labels left out and why, and the subject columns no label uses."""
    provenance = getattr(sm, "provenance_", {})
    unknown = "not recorded (fitted by an earlier version; refit with --database DB --refit)"
    lines = [f"{name}: {describe_source(name, provenance[name]) if name in provenance else unknown}"
             for name in sm.labels_]
    lines += [f"{name}: not learned: {why}" for name, why in getattr(sm, "skipped_", {}).items()]
    unused = getattr(sm, "unused_columns_", [])
    if unused:
        source = next((p["source"] for p in provenance.values()), "the subject table")
        lines.append(f"columns of {source} no label uses: {', '.join(unused)}")
    return lines


def generate(model_file: Path = typer.Argument(..., help="Model file (.npz, bodyspace build)."),
             sets: Optional[List[str]] = SetOption, ranges: Optional[List[str]] = RangeOption,
             out: Path = typer.Option(..., "--out", help="Mesh file to write (.obj, .ply or .glb; metres)."),
             seed: int = SeedOption("Random seed for what is not asked (an integer >= 0)."),
             clamp: bool = ClampOption, database: Optional[Path] = DatabaseOption, refit: bool = RefitOption,
             accept_misses: bool = AcceptMissesOption, force: bool = ForceOption,
             rig: Optional[str] = RigOption, morphs: Optional[str] = MorphsOption, png: Optional[Path] = PngOption,
             bones: Optional[str] = BonesOption):
    """A body that measures what is asked (labels such as stature, mass, sex within 4 mm / 0.5 kg, and any length of
    the measurement set, e.g. waist_size, shoulder_width, within 1 mm by exact refinement); the rest at random."""
    check_file_output(out, "--out", force, MESH_SUFFIXES, example="body.obj")
    rigged = None
    try:
        check_rig_options(out, rig, morphs, png, bones, force)
        if not sets and not ranges:
            raise BodyspaceError("nothing asked; pass --set NAME=VALUE, e.g. --set stature=180cm")
        sm = load_semantics(model_file, database, refit, clamp)
        targets = parse_targets(sets, ranges, allow_delta=False, sm=sm)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", RuntimeWarning)
            result = sm.body_model.generate(targets, rng=seed, accept_misses=accept_misses)
            if rig is not None:  # a rigged glTF (cli.export): skeleton, skin weights, morph targets
                rigged = write_rigged(out, result.vertices, sm.body_model.faces, rig, body_model=sm.body_model,
                                      morphs=morphs, png=png, bones=bones, where=f"{model_file} (its bodies)")
        if rig is None:
            _save_mesh(out, result.vertices, sm.body_model.faces)
    except BodyspaceError as exc:
        _fail(exc)
    _report_warnings(caught)
    if rigged:
        console.print(rigged, highlight=False)
    out_console.print(_result_table(f"generated {out.name}", result, sm))
    out_console.print(f"wrote {out}: {result.iterations} correction(s), {result.mahalanobis:.2f} SD from the random "
                      "start", highlight=False)


def morph(model_file: Path = typer.Argument(..., help="Model file (.npz, bodyspace build)."),
          mesh: Path = typer.Argument(..., help="A registered body mesh (the model's template topology)."),
          sets: Optional[List[str]] = SetOption,
          keep: Optional[List[str]] = typer.Option(None, "--keep", help="Variables to hold, e.g. --keep mass."),
          mask: Optional[List[str]] = typer.Option(None, "--mask", help="Confine the change to a region: upper_body, "
                                                   "lower_body, arms, legs, torso, head, left, right (repeatable)."),
          out: Path = typer.Option(..., "--out", help="Mesh file to write (.obj, .ply or .glb; metres)."),
          detail: Optional[Path] = typer.Option(None, "--detail", help="detail.npz of bodyspace register --detail "
                                                "(MESH its registered_standard.obj): the scan's relief re-added "
                                                "on the morphed body (the output is then the subdivided mesh)."),
          clamp: bool = ClampOption, database: Optional[Path] = DatabaseOption, refit: bool = RefitOption,
          accept_misses: bool = AcceptMissesOption,
          as_posed: bool = typer.Option(False, "--as-posed", help="Morph and measure the mesh as it is. By default "
                                        "a posed body (a registered scan in a T-pose, elbows bent) is brought "
                                        "back to standing, morphed and measured there as bodyspace measure "
                                        "measures it, and the change is posed back onto the mesh."),
          force: bool = ForceOption):
    """Change a body: --set stature=+5cm --keep mass ("taller, same weight"), optionally within a --mask."""
    check_file_output(out, "--out", force, MESH_SUFFIXES, example="body.obj")
    try:
        if not sets:
            raise BodyspaceError("nothing to change; pass --set NAME=VALUE or NAME=+CHANGE, e.g. --set stature=+5cm")
        relief = load_detail(detail) if detail is not None else None
        sm = load_semantics(model_file, database, refit, clamp)
        changes = parse_targets(sets, None, allow_delta=True, sm=sm)
        v, f = load_mesh(mesh)
        if v.shape != sm.body_model.template_vertices.shape or not np.array_equal(f, sm.body_model.faces):
            raise BodyspaceError(f"{mesh}: {len(v)} vertices / {len(f)} faces, expected the model's template topology "
                                 f"({len(sm.body_model.template_vertices)} vertices, {len(sm.body_model.faces)} faces)")
        standing, posed_back, note = _morph_standing(v, f, mesh, as_posed)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", RuntimeWarning)
            result = sm.body_model.morph(standing, changes, keep=list(keep or []), mask=list(mask) if mask else None,
                                         accept_misses=accept_misses)
        morphed = posed_back(result.vertices)
        if relief is None:
            _save_mesh(out, morphed, f)
        else:
            _save_mesh(out, *apply_detail(morphed, f, relief, name=f"{mesh} (--detail {detail})"))
    except BodyspaceError as exc:
        _fail(exc)
    _report_warnings(caught)
    if note:
        console.print(f"[unposed] {mesh.name}: {note}", markup=False, highlight=False, soft_wrap=True)
    out_console.print(_result_table(f"morphed {mesh.name}" + (f" within {', '.join(mask)}" if mask else ""), result,
                                    sm))
    moved = np.linalg.norm(morphed - v, axis=1)
    out_console.print(f"wrote {out}: {result.iterations} correction(s); vertices moved up to {1000 * moved.max():.1f} mm"
                      f"{'' if relief is None else f'; the relief of {detail} re-added ({relief.describe()})'}",
                      highlight=False)


# A body whose largest part is turned less than this from the rest pose is morphed as it is: the
# model's own bodies and standing scans (unposing them would only add its small residual).
MORPH_UNPOSE_DEG = 10.0


def _morph_standing(vertices: np.ndarray, faces: np.ndarray, mesh: Path, as_posed: bool):
    """The body to morph and how to put its change back on the mesh: ``(standing (V, 3),
    posed_back(morphed standing (V, 3)) -> (V, 3), note or None)``.

    The model's change is a change of a standing body: added to a T-posed registered scan, the arms'
    change went along the arms' rest direction and the measurements were taken on the posed mesh
    (stature and mass of the morph 1 cm and 1 kg off what ``bodyspace measure`` reads on it). A
    posed mesh of the template's topology is unposed with the default rig (as ``measure`` does),
    morphed standing, and the change posed with the body's own rotations and added to the mesh,
    so the scan's own surface and pose stay as they were.
    """
    def same(x):
        return x

    template = load_template()
    if as_posed or not fits_template(vertices, faces, template):
        return vertices, same, None
    rig = template.rigs["default"]
    try:
        rest, rotations, info = unpose(vertices, rig, mesh_name=str(mesh))
    except UnposeError as exc:
        raise UnposeError(f"{exc} (--as-posed morphs the mesh as it is, without unposing)") from None
    if float(info.largest_rotation_deg) < MORPH_UNPOSE_DEG:
        return vertices, same, None
    posed_rest = pose_bodies(rest, rig, rotations)

    def posed_back(morphed):
        return vertices + (pose_bodies(morphed, rig, rotations) - posed_rest)

    return rest, posed_back, (f"morphed standing: the body was brought back to the rest pose ({info.describe()}), "
                              "morphed and measured there, and the change posed back onto the mesh; --as-posed "
                              "morphs the mesh as it is")


def crowd(model_file: Path = typer.Argument(..., help="Model file (.npz, bodyspace build)."),
          n: int = typer.Option(20, "-n", "--number", min=1, help="Number of bodies."),
          sets: Optional[List[str]] = SetOption, ranges: Optional[List[str]] = RangeOption,
          out: Path = typer.Option(..., "--out", help="Output folder: meshes, crowd.csv, lineup.png "
                                                      "(must not exist, see --force)."),
          fmt: str = typer.Option("obj", "--format", help="Mesh format: obj, ply or glb."),
          seed: int = SeedOption(),
          png: bool = typer.Option(True, "--png/--no-png", help="Write the line-up lineup.png."),
          clamp: bool = ClampOption, database: Optional[Path] = DatabaseOption, refit: bool = RefitOption,
          accept_misses: bool = AcceptMissesOption, force: bool = ForceOption):
    """A crowd meeting the request (values or ranges), the rest random: meshes, a CSV of measurements, a PNG line-up."""
    check_folder_output(out, "--out", force, CROWD_KIND)
    try:
        if fmt.lower() not in ("obj", "ply", "glb"):
            raise BodyspaceError(f"--format {fmt!r}, expected obj, ply or glb")
        sm = load_semantics(model_file, database, refit, clamp)
        targets = parse_targets(sets, ranges, allow_delta=False, sm=sm)
        bm = sm.body_model
        check_bodies_fit(n, fmt.lower(), bm.n_components, len(bm.template_vertices), len(bm.faces), out)
        with _progress("crowd") as cb, warnings.catch_warnings(record=True) as caught, \
                output_folder(out, "--out", force, CROWD_KIND) as folder:
            warnings.simplefilter("always", RuntimeWarning)
            model = sm.body_model
            names = [f"body_{i:0{max(3, len(str(n - 1)))}d}.{fmt.lower()}" for i in range(n)]
            # One body at a time (or SAMPLE_CHUNK random ones), written as it is made: memory does
            # not grow with -n; the line-up keeps the first SHEET_MAX.
            if targets:
                made = ((r.vertices, r.coefficients, r) for r in
                        model.iter_crowd(n, targets, rng=seed, accept_misses=accept_misses))
            else:   # nothing asked: random bodies from the shape-only model, their coefficients known
                made = _random_bodies(model, model.sample_coefficients(n, sigma_range=2.0, rng=seed))
            sheet, missed = [], 0
            with open(folder / "crowd.csv", "w", newline="") as fh:
                writer = None
                for i, (name, (body, c, result)) in enumerate(zip(names, made)):
                    _save_mesh(folder / name, body, model.faces)
                    meas = to_json(_measure_one(sm, body))
                    row = {"mesh": name}
                    if result is not None:
                        row["converged"] = result.converged
                        row["iterations"] = result.iterations
                        missed += not result.converged
                    c = np.asarray(c, dtype=float).reshape(-1)
                    for lab in sm.labels_:
                        if lab not in sm.measured_:
                            row[f"{lab} (model)"] = round(float(sm.regressors_[lab].predict(c)), 4)
                    row.update({f"{k} ({e['unit']})": e["value"] for k, e in meas.items()})
                    if writer is None:
                        writer = csv.DictWriter(fh, fieldnames=list(row))
                        writer.writeheader()
                    writer.writerow(row)
                    if i < SHEET_MAX:
                        sheet.append(body)
                    cb(f"wrote {name}", 0.9 * (i + 1) / n)
            if png:
                cb("rendering lineup.png", 0.9)
                shown = f" (the first {len(sheet)})" if n > len(sheet) else ""
                contact_sheet(np.asarray(sheet), model.faces, folder / "lineup.png", labels=names[:len(sheet)],
                              title=f"crowd of {n}{shown}: "
                                    + (", ".join(sets or []) + " " + ", ".join(ranges or [])).strip())
            cb("done", 1.0)
    except BodyspaceError as exc:
        _fail(exc)
    _report_warnings(caught)
    out_console.print(f"wrote {n} bodies, crowd.csv" + (" and lineup.png" if png else "") + f" to {out}"
                      + (f"; {missed} missed a target (see warnings)" if missed else ""), highlight=False)


def _random_bodies(model: BodyModel, coefficients: np.ndarray):
    """(body (V, 3), its coefficients (K,), None) for each row of ``coefficients`` (N, K),
    decoded SAMPLE_CHUNK at a time."""
    for start in range(0, len(coefficients), SAMPLE_CHUNK):
        chunk = coefficients[start:start + SAMPLE_CHUNK]
        for body, c in zip(model.reconstruct(chunk), chunk):
            yield body, c, None


def _measure_one(sm, body):
    return evaluate_measurements(sm.mset, body, sm.body_model.faces)

