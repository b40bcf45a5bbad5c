"""Run the leave-one-subject-out generalization study (issue 12 §4) at every component count,
"all" included, which the demo leaves out of its pose+shape study for time.

Run: python benchmarks/study_generalization.py DB OUT [folds] [--without-all]
[--selections rest,all] [--bases code,vertex,refined]
DB is a scan database (e.g. the demo's ``bodyspace-demo/population``), OUT a new folder for
``generalization.{md,json,png}``. The RRE models are fitted as the demo fits them and measured
with the asked component orders (``ShapeSpace(basis="code"|"vertex"|"refined")``, default code
and vertex) and both projections; ``folds`` is how many held-out subjects (default 2; the number
of subjects for every fold). At all ~140 components of the pose+shape study the vertex fit takes
tens of seconds a mesh on two cores, so the whole run takes on the order of an hour;
``--without-all`` stops at k = 32. The "refined" basis refines the vertex order on the training
scans of every fold (``shape.refine``: minutes a fold on 138 posed scans).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from bodyspace.data.database import ScanDatabase
from bodyspace.data.template import load_template
from bodyspace.encoding import VertexEncoder
from bodyspace.model import BodyModel
from bodyspace.report.shape_report import write_generalization_report
from bodyspace.studies.generalization import DEFAULT_COMPONENTS, generalization_study


def main(argv: list[str]) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("db")
    ap.add_argument("out")
    ap.add_argument("folds", nargs="?", type=int, default=2)
    ap.add_argument("--without-all", action="store_true")
    ap.add_argument("--selections", default="rest,all")
    ap.add_argument("--bases", default="code,vertex")
    args = ap.parse_args(argv)
    db = ScanDatabase.load(args.db)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=False)
    template = load_template()
    t = time.perf_counter()
    results = []
    for selection in args.selections.split(","):
        model = BodyModel.fit(db, "rre", selection, template=template, on_flipped="ignore")
        rows = np.asarray(db.rest_rows() if selection == "rest" else np.arange(db.n_scans))
        vertex = VertexEncoder(template.vertices, template.faces).fit(np.asarray(db.read(rows), dtype=float))
        results.append(generalization_study(db, {"rre": model.encoder, "vertex": vertex}, selection=selection,
                                            n_folds=args.folds, components=DEFAULT_COMPONENTS,
                                            bases=tuple(args.bases.split(",")), with_all_components=not args.without_all,
                                            progress=lambda m, f: print(f"{selection}: {m} ({f:.0%})", flush=True)))
    files = write_generalization_report(results, out)
    print(f"wrote {', '.join(str(v) for v in files.values())} in {time.perf_counter() - t:.0f} s")


if __name__ == "__main__":
    main(sys.argv[1:])
