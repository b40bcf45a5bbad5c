"""The phenotype shape space's size (issue 15): 60 components (``PHENOTYPE_COMPONENTS``) against 24.

Per test scan (bench_register's seeds, poses and point counts), in one process, one after the
other: ``register_scan`` with the 24-component and with the 60-component ``phenotype_basis``
(both built before timing), this process's CPU time, the correspondence and surface errors and
the ISO 20685-1 count of the fit's measurements (bench_register's). Prints the CPU ratio.

    python benchmarks/bench_shape_basis.py [--only 0] [--landmarks]
"""

from __future__ import annotations

import argparse
import os
import time

from _common import report
from bench_register import POSES, landmarks_and_measurements
from bodyspace.data.template import load_template
from bodyspace.measure.definitions import load_measurement_set
from bodyspace.register.model_fit import PHENOTYPE_COMPONENTS, phenotype_basis
from bodyspace.register.pipeline import register_scan
from bodyspace.studies.registration import SURFACE_LANDMARKS, registration_errors
from bodyspace.synth.phenotype import PhenotypeModel
from bodyspace.synth.scans import raw_scan

POINTS = (50000, 100000, 150000, 200000)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--only", default="0", help="comma list of bench_register's scan numbers")
    ap.add_argument("--landmarks", action="store_true", help="register with the 13 surface landmarks")
    args = ap.parse_args()
    template = load_template()
    pm = PhenotypeModel(template)
    mset = load_measurement_set()
    bases = {k: phenotype_basis(template, n_components=k) for k in (24, PHENOTYPE_COMPONENTS)}  # kept: the cache holds one
    cpu = {k: 0.0 for k in bases}
    for i in (int(s) for s in args.only.split(",")):
        scan = raw_scan(template, pm, 100 + i, pose=POSES[i % len(POSES)], n_points=POINTS[i % len(POINTS)])
        truth_rest = pm.vertices(scan.phenotype[None])[0]
        lms = {n: scan.landmarks[n] for n in SURFACE_LANDMARKS} if args.landmarks else None
        for k, basis in bases.items():
            c = time.process_time()
            v = register_scan(scan.points, template=template, landmarks=lms, basis=basis, check=False).vertices
            sec = time.process_time() - c
            cpu[k] += sec
            e = registration_errors(v, template.faces, scan)
            _, iso = landmarks_and_measurements(v, scan, template, mset, truth_rest)
            print(f"scan {i} ({scan.pose}), {k} components: correspondence {e['correspondence_mm']:.2f} mm, surface "
                  f"{e['surface_mm']:.2f} mm, folded {e['folded']}, ISO 20685-1 {iso[0]}/{iso[1]}, CPU {sec:.1f} s "
                  f"(load {os.getloadavg()[0]:.1f})", flush=True)
    report(f"register_scan, {PHENOTYPE_COMPONENTS} vs 24 components (CPU)", cpu[PHENOTYPE_COMPONENTS], cpu[24], 1000,
           "milliscans")


if __name__ == "__main__":
    main()
