"""Run the leave-one-subject-out generalization study (issue 12 §4) at every component count,
"all" included, which the demo leaves out of its pose+shape study for time.

Run: python benchmarks/study_generalization.py DB OUT [folds] [--without-all]
DB is a scan database (e.g. the demo's ``bodyspace-demo/population``), OUT a new folder for
``generalization.{md,json,png}``. The RRE models are fitted as the demo fits them and measured
with both component orders (``ShapeSpace(basis="code"|"vertex")``) and both projections. At all
~140 components of the pose+shape study the vertex fit takes tens of seconds a mesh on two
cores, so the whole run takes on the order of an hour; ``--without-all`` stops at k = 32.
"""

from __future__ import annotations

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
    with_all = "--without-all" not in argv
    argv = [a for a in argv if a != "--without-all"]
    if len(argv) < 2:
        sys.exit(__doc__)
    db = ScanDatabase.load(argv[0])
    out = Path(argv[1])
    out.mkdir(parents=True, exist_ok=False)
    folds = int(argv[2]) if len(argv) > 2 else 2
    template = load_template()
    t = time.perf_counter()
    results = []
    for selection in ("rest", "all"):
        model = BodyModel.fit(db, "rre", selection, template=template, on_flipped="ignore")
        rows = np.asarray(db.rest_rows() if selection == "rest" else np.arange(db.n_scans))
        vertex = VertexEncoder(template.vertices, template.faces).fit(np.asarray(db.read(rows), dtype=float))
        results.append(generalization_study(db, {"rre": model.encoder, "vertex": vertex}, selection=selection,
                                            n_folds=folds, components=DEFAULT_COMPONENTS,
                                            bases=("code", "vertex"), with_all_components=with_all,
                                            progress=lambda m, f: print(f"{selection}: {m} ({f:.0%})", flush=True)))
    files = write_generalization_report(results, out)
    print(f"wrote {', '.join(str(v) for v in files.values())} in {time.perf_counter() - t:.0f} s")


if __name__ == "__main__":
    main(sys.argv[1:])
