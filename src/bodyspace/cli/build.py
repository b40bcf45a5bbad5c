"""``bodyspace build``: a BodyModel file from a scan database.

Its own module (not beside ``sample`` in ``cli.model``): ``build`` draws nothing, so it does not
import the report modules and matplotlib (half a second at every start)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from bodyspace.cli.common import (
    MESH_SUFFIXES,
    ForceOption,
    check_choice,
    check_file_output,
    console,
    out_console,
    progress,
)
from bodyspace.data.database import LANDMARKS_FILE, META_FILE, ScanDatabase
from bodyspace.errors import DatabaseError, ParameterError
from bodyspace.measure import load_measurement_set
from bodyspace.model import ON_FLIPPED, BodyModel
from bodyspace.shape import BASES


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
          landmarks: Optional[Path] = typer.Option(None, "--landmarks",
                                                   help="Landmark file of the scans' topology (JSON {\"landmarks\": "
                                                        "{name: vertex id or {\"vertices\": [...], \"weights\": "
                                                        "[...]}}}, docs/measurements.md): the model keeps the "
                                                        "measurement set it gives. Default: DATABASE/landmarks.json "
                                                        "if present, else the built-in set for the template's "
                                                        "topology."),
          basis: str = typer.Option("code", "--basis",
                                    help="Order of the PCA components: code (by code variance, Hasler) or vertex "
                                         "(by the vertex-space variance they carry: an RRE model's first components "
                                         "then move whole limbs) or refined (the vertex order refined for fitting "
                                         "meshes: a few vertex fits of every scan; docs/encoding.md)."),
          scratch: Optional[Path] = typer.Option(None, "--scratch", help="Folder for the code file of a large build "
                                                 "(the codes of every scan, N x D x 4 bytes, read in blocks by the "
                                                 "PCA so memory does not grow with N; kept when the build is "
                                                 "killed, so the same command continues it). Default: the "
                                                 "system's temporary folder (TMPDIR)."),
          force: bool = ForceOption):
    """Build a BodyModel (template, encoder statistics, PCA shape space, measurement set) from a scan database."""
    check_file_output(out, "--out", force, (".npz",), example="model.npz")
    on_flipped = check_choice(on_flipped, "--on-flipped", ON_FLIPPED)
    basis = check_choice(basis, "--basis", BASES)
    _check_not_mesh_folder(database)
    if landmarks is not None and not landmarks.is_file():
        raise ParameterError(f"--landmarks {landmarks}: no such file; expected a landmark file (JSON, "
                             "docs/measurements.md)")
    if scratch is not None and not scratch.is_dir():
        raise ParameterError(f"--scratch {scratch}: not a folder; give an existing folder with room for the codes")
    db = ScanDatabase.load(database)
    with progress("build", eta=True) as cb:
        model = BodyModel.fit(db, encoding, selection, components, on_flipped=on_flipped, landmarks=landmarks,
                              basis=basis, progress=cb, scratch=scratch,
                              log=lambda line: console.print(line, highlight=False, soft_wrap=True))
    model.save(out)
    folded = model.provenance.get("flipped_scans")
    if folded:
        console.print(f"{folded} of {len(model.fitted_scans)} scan(s) have flipped (folded) triangles (at most "
                      f"{model.provenance['flipped_triangles_max']} in a scan); encoded anyway (--on-flipped "
                      f"{on_flipped}; raise refuses them)", highlight=False)
    console.print(_measurement_set_line(model, database), soft_wrap=True, highlight=False)
    ratio = float(model.space.explained_variance_ratio_.sum())
    t = model.provenance["timings_s"]
    out_console.print(f"wrote {out}: {model!r}; {100 * ratio:.1f}% of the variance; "
                      f"encode {t['encode_s']:.1f} s, PCA {t['pca_s']:.1f} s, total {t['total_s']:.1f} s")


def _measurement_set_line(model: BodyModel, database: Path) -> str:
    """What the model measures with, said after build (and what to do when it has nothing)."""
    if not model.has_measurement_set:
        return (f"no measurement set: the scans ({len(model.template_vertices)} vertices) are not of the template's "
                "topology and no landmark file was given, so measure --model, generate, morph, crowd, evaluate and "
                f"mapping cannot use this model; build it again with --landmarks FILE (or put {LANDMARKS_FILE} in "
                f"{database})")
    mset = model.measurement_set
    loops = [m["name"] for m in load_measurement_set().measurements if m["method"] == "loop"
             and m["name"] not in mset.names]
    return (f"measurement set: {len(mset.names)} measurements from {mset.source}"
            + (f" (the template's vertex loops {', '.join(loops)} do not exist on this topology)" if loops else ""))


def _check_not_mesh_folder(folder: Path) -> None:
    """Refuse a folder of meshes given where a scan database is expected, with the command
    that turns it into one (instead of ScanDatabase.load's "missing meta.json")."""
    if folder.is_dir() and not (folder / META_FILE).is_file():
        meshes = [p for p in folder.iterdir() if p.suffix.lower() in MESH_SUFFIXES + (".stl",)]
        if meshes:
            raise DatabaseError(f"{folder} is a folder of meshes, not a scan database; run `bodyspace import "
                                f"{folder} --labels CSV --out DB` first, then `bodyspace build DB` "
                                f"({len(meshes)} mesh file(s), e.g. {meshes[0].name}, and no {META_FILE})")
