"""Benchmark: the mapping and the semantic requests on a model of another topology (issue 12 §2).

The same people twice: a user-style scan folder (``synth.foreign.write_scan_folder``: 30
subjects in the A-pose, one remeshed topology of 6,000 vertices, mm, turned, off the origin;
imported with its landmark file) and the same subjects' rest bodies on the template (13,380
vertices, the shipped set). A shape-only vertex model of each (not timed). Printed, in one run:

  * the model-file round trip of the measurement set (save + load of the foreign model) and the
    regions derived from its landmarks (``region_weights_from_landmarks``, once per model);
  * the training set (1,000 bodies; the mapping's inputs: Rupprecht's six on the template, their
    ISO stand-ins on the foreign topology, four of them slices) against the naive per-body
    loop (reconstruct + measure one body at a time, timed on 100 and scaled) on the foreign model;
  * exact refinement, ms per request over 100 held-out requests, foreign (slices: forward
    differences through batched reconstruct + measure) against the template (analytic Jacobians),
    and the share within 1 mm;
  * ``generate`` of stature + mass + waist girth (semantic loop + exact refinement), foreign
    against template.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import report  # noqa: E402

from bodyspace.data.database import ScanDatabase  # noqa: E402
from bodyspace.data.template import load_template  # noqa: E402
from bodyspace.mapping.bundle import fit_mapping  # noqa: E402
from bodyspace.mapping.refine import refine  # noqa: E402
from bodyspace.mapping.training import make_training_set, sample_uniform  # noqa: E402
from bodyspace.measure import measure  # noqa: E402
from bodyspace.model import BodyModel  # noqa: E402
from bodyspace.rig.posing import pose_bodies  # noqa: E402
from bodyspace.semantics.masks import region_weights_from_landmarks  # noqa: E402
from bodyspace.semantics.model import SemanticModel  # noqa: E402
from bodyspace.synth.foreign import write_scan_folder  # noqa: E402
from bodyspace.synth.phenotype import PhenotypeModel  # noqa: E402
from bodyspace.synth.poses import load_pose_library  # noqa: E402


def models(subjects: int, vertices: int, tmp: Path):
    """(foreign model, foreign db, template model, template db): the same subjects' rest bodies."""
    template = load_template()
    pm = PhenotypeModel(template)
    folder = write_scan_folder(template, pm, tmp / "scans", subjects, 0, target_vertices=vertices, rng=0)
    fdb = ScanDatabase.from_meshes(folder.folder, folder.labels_csv, length_unit="mm", rest_pose="a_pose")
    fdb.save(tmp / "fdb", extra_files={"landmarks.json": folder.landmarks_json.read_text()})
    fdb = ScanDatabase.load(tmp / "fdb")
    foreign = BodyModel.fit(fdb, "vertex")
    rig = template.rigs["default"]
    rest = pose_bodies(pm.vertices(folder.subjects.phenotypes), rig, load_pose_library().rotations("rest", rig),
                       on_ground=True)
    tdb = ScanDatabase(rest, template.faces, fdb.subjects, {"subject": fdb.scans["subject"],
                                                            "pose": np.array(["rest"] * subjects)},
                       {"template": template.template_id})
    return foreign, fdb, BodyModel.fit(tdb, "vertex", template=template), tdb


def naive_measure(model, z, names):
    out = np.empty((len(z), len(names)))
    for i, zi in enumerate(z):
        m = measure(model.measurement_set, model.reconstruct(zi)[0], model.faces)
        out[i] = [100 * m[n] for n in names]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", type=int, default=30)
    ap.add_argument("--vertices", type=int, default=6000)
    ap.add_argument("--samples", type=int, default=1000)
    ap.add_argument("--held-out", type=int, default=100)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        foreign, fdb, tmpl, tdb = models(args.subjects, args.vertices, Path(tmp))
        print(f"models: {foreign!r} and {tmpl!r} in {time.perf_counter() - t:.1f} s (not timed)")

        # 1. the measurement set in the model file, the regions from the landmarks
        t = time.perf_counter()
        back = BodyModel.load(foreign.save(Path(tmp) / "f.npz"))
        io_s = time.perf_counter() - t
        assert back.measurement_set.measurements == foreign.measurement_set.measurements
        t = time.perf_counter()
        regions = region_weights_from_landmarks(foreign.mean_vertices, foreign.measurement_set)
        print(f"save + load of the foreign model (with its measurement set): {1000 * io_s:.0f} ms; regions from the "
              f"landmarks: {1000 * (time.perf_counter() - t):.1f} ms ({len(regions)} regions)")

    trained = {}
    for label, model in (("foreign", foreign), ("template", tmpl)):
        t = time.perf_counter()
        train = make_training_set(model, args.samples, 25, rng=0)
        trained[label] = (train, time.perf_counter() - t)
        print(f"{label}: training set of {args.samples}: {trained[label][1]:.2f} s, inputs {', '.join(train.names)}")
    train, fast = trained["foreign"]
    n_naive = 100
    z = sample_uniform(foreign, n_naive, 25, rng=0)
    t = time.perf_counter()
    ref = naive_measure(foreign, z, train.names)
    naive = (time.perf_counter() - t) * args.samples / n_naive
    diff = np.nanmax(np.abs(ref - train.measurements[:n_naive]))
    print(f"foreign naive per-body loop (scaled from {n_naive}): {naive:.1f} s; max difference {diff:.1e} cm")
    report("foreign training set", fast, naive, args.samples, "bodies")
    report("training set, template (analytic loops) vs foreign (slices)", trained["template"][1], fast,
           args.samples, "bodies")

    # 2. refinement from the forest's prediction
    per = {}
    for label, model in (("foreign", foreign), ("template", tmpl)):
        model.mapping = fit_mapping(model, args.samples, rng=0, n_trees=20)
        held = make_training_set(model, args.held_out, 25, rng=1)
        z0 = model.mapping.predict(held.measurements)
        t = time.perf_counter()
        r = refine(model, z0, held.measurements, held.names, k=model.mapping.k)
        per[label] = (time.perf_counter() - t) / args.held_out
        print(f"{label}: refinement {1000 * per[label]:.2f} ms/request, {100 * r.met.mean():.0f} % within 1 mm, "
              f"{r.iterations.mean():.1f} iterations")
    report("refinement, template vs foreign", per["template"], per["foreign"], 1, "requests")

    # 3. generate: stature, mass and a girth, met by the closed loop and the exact refinement
    gen = {}
    for label, model, db in (("foreign", foreign, fdb), ("template", tmpl, tdb)):
        model.semantics = SemanticModel(model).fit(db)
        asked = {"stature": 1.70, "mass": 68.0, "waist_girth": 0.84}
        model.generate(asked, rng=0)
        t = time.perf_counter()
        res = [model.generate(asked, rng=s) for s in range(5)]
        gen[label] = (time.perf_counter() - t) / 5
        print(f"{label}: generate {1000 * gen[label]:.0f} ms, {sum(r.converged for r in res)}/5 met")
    report("generate, template vs foreign", gen["template"], gen["foreign"], 1, "bodies")


if __name__ == "__main__":
    main()
