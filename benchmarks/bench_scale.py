"""Scale on one machine (issue 16): wall time, peak memory and disk of population, build (both
encodings) and measure at growing N, the fitted growth, and the Krylov PCA with its codes in
memory against the same PCA reading them from disk.

Each command runs as the user runs it (``python -m bodyspace ...``) in a child process. Its
peak memory is that of the child and its worker processes together, sampled (``_treemem``: the
sum of their proportional set sizes, PSS, and the larger sum of their resident sizes, RSS, which
counts the pages a forked worker shares with its parent twice); disk is the size of what it
wrote. The population runs twice at each N: ``--workers 1`` (the baseline) and one worker per
core, and the speed-up is printed as a ratio. The PCA comparison runs in this process on the codes of one build (the baseline:
the in-memory fit, same codes, same start block).

    PYTHONPATH=src python benchmarks/bench_scale.py --scans 1000 5000 [--keep DIR]
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import report  # noqa: E402
from _treemem import TreeMemory  # noqa: E402

from bodyspace.data.database import ScanDatabase  # noqa: E402
from bodyspace.encoding import ENCODERS  # noqa: E402
from bodyspace.model import BodyModel  # noqa: E402
from bodyspace.rowfile import RowFile  # noqa: E402
from bodyspace.shape import ShapeSpace  # noqa: E402

POSES = 4  # scans per subject: rest + 4 poses


def _spawn_measured(args: list[str]) -> tuple[float, float, float, float, str]:
    """(wall s, CPU s, peak PSS GB, peak RSS GB, its summary lines) of ``python -m bodyspace
    ARGS``: memory summed over the child and its workers (``TreeMemory``), CPU from the child's
    rusage (``os.wait4``: its own and that of the workers it reaped)."""
    t = time.perf_counter()
    with tempfile.TemporaryFile("w+") as log:
        child = subprocess.Popen([sys.executable, "-c", _WRAPPER, *args], stdout=log, stderr=log,
                                 env={**os.environ, "COLUMNS": "200"})
        with TreeMemory(child.pid) as tree:
            _, status, usage = os.wait4(child.pid, 0)
        child.returncode = os.waitstatus_to_exitcode(status)
        wall = time.perf_counter() - t
        log.seek(0)
        text = log.read()
    if child.returncode:
        raise SystemExit(f"bodyspace {' '.join(args)} failed:\n{text[-2000:]}")
    lines = [ln for ln in text.strip().splitlines() if ln.startswith(("wrote", "1 ", "no subject")) or "redrawn" in ln]
    workers = [ln.split()[1:] for ln in text.splitlines() if ln.startswith("bench-workers")]
    # A sample can miss a short peak: never report less than the largest single process.
    single_gb = max([usage.ru_maxrss] + [int(w[0]) for w in workers]) / 2**20
    # wait4's rusage already includes the descendants the child reaped (its workers): adding the
    # workers' own line as well counted them twice (the RESULTS tables before 2026-12-03 did).
    cpu = usage.ru_utime + usage.ru_stime
    return (wall, cpu, max(tree.peak_pss_gb, single_gb), max(tree.peak_rss_gb, single_gb),
            " | ".join(lines)[-300:])


# The command as `python -m bodyspace ARGS` runs it, then the peak RSS and CPU seconds of its own
# worker processes (measure's forked pool; reaped before it exits, so RUSAGE_CHILDREN has them).
_WRAPPER = """
import resource, sys
from bodyspace.cli import main
sys.argv = ["bodyspace"] + sys.argv[1:]
try:
    main()
except SystemExit as exc:
    code = exc.code
else:
    code = 0
workers = resource.getrusage(resource.RUSAGE_CHILDREN)
print("bench-workers", workers.ru_maxrss, workers.ru_utime + workers.ru_stime, file=sys.stderr)
sys.exit(code)
"""


def cores_obtained(processes: int, seconds: float = 2.0) -> float:
    """CPU cores that ``processes`` busy forked processes of this session get now (CPU s / wall s).

    On a machine shared with other sessions, Linux's autogroup scheduling divides the CPU between
    sessions, not processes: then two workers get no more than one, and no number of workers can
    show a speed-up. Printed before the runs so the ratios can be read against it."""
    pids = []
    for _ in range(processes):
        pid = os.fork()
        if pid == 0:
            end = time.perf_counter() + seconds
            while time.perf_counter() < end:
                pass
            os._exit(0)
        pids.append(pid)
    cpu = 0.0
    for pid in pids:
        _, _, usage = os.wait4(pid, 0)
        cpu += usage.ru_utime + usage.ru_stime
    return cpu / seconds


def disk_gb(path: Path) -> float:
    if path.is_file():
        return path.stat().st_size / 1e9
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) / 1e9


def fitted_growth(ns: list[int], values: list[float]) -> str:
    """``value ∝ N^b``: the exponent b of a least-squares line in log-log (1 = linear)."""
    if len(ns) < 2:
        return "n/a"
    b, _ = np.polyfit(np.log(ns), np.log(values), 1)
    return f"N^{b:.2f}"


def pca_side_by_side(db_folder: Path, scratch: Path, k: int = 100) -> None:
    """The Krylov PCA of the RRE codes of every scan, in memory and from a RowFile on disk."""
    db = ScanDatabase.load(db_folder, check_values=False)
    rows = np.arange(db.n_scans)
    encoder = ENCODERS["rre"](np.asarray(db.rest_pose().vertices[0], float), db.faces).fit(db.read(rows[:64]))
    d = encoder.n_features_
    codes = RowFile.create(scratch / "codes.npy", (len(rows), d), np.float32)
    for s, x in db.iter_chunks(rows, 64):
        codes.write(s, encoder.encode(x).astype(np.float32))
    k = min(k, len(rows) - 1)
    results = {}
    for where in ("memory", "disk"):
        x = codes.read(0, len(rows)) if where == "memory" else codes
        tracemalloc.start()
        t = time.perf_counter()
        space = ShapeSpace(n_components=k, solver="krylov", rng=0).fit(x)
        wall = time.perf_counter() - t
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        held = codes.nbytes if where == "memory" else 0
        results[where] = (wall, float(space.explained_variance_ratio_.sum()), (peak + held) / 1e9)
        del x
    (codes.path).unlink()
    print(f"\nPCA (block Krylov, {k} components) of {len(rows)} RRE codes of length {d} "
          f"({len(rows) * d * 4 / 1e9:.2f} GB float32):")
    print("| codes | wall | captured variance | peak numpy memory (tracemalloc, + codes held) |")
    print("|---|---|---|---|")
    for where, (wall, ratio, peak) in results.items():
        print(f"| {where} | {wall:.1f} s | {100 * ratio:.4f} % | {peak:.2f} GB |")
    report("out-of-core PCA", results["disk"][0], results["memory"][0], len(rows), "codes")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=int, nargs="+", default=[1000, 5000])
    parser.add_argument("--keep", type=Path, default=None, help="work folder (default: a temporary one)")
    parser.add_argument("--skip", nargs="*", default=[], help="stages to skip: population-1-worker population "
                                                               "build-rre build-vertex measure measure-posed pca")
    parser.add_argument("--baseline-scans", type=int, nargs="*", default=None,
                        help="the N at which the --workers 1 population baseline runs (default: every N)")
    parser.add_argument("--pca-scans", type=int, default=1000, help="size of the PCA side-by-side (0: skip)")
    args = parser.parse_args()
    work = args.keep or Path(tempfile.mkdtemp(prefix="bench-scale-"))
    work.mkdir(parents=True, exist_ok=True)
    print(f"bench_scale: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}, work in {work}; "
          f"cores one / two busy processes of this session get now: {cores_obtained(1):.2f} / "
          f"{cores_obtained(2):.2f}", flush=True)
    rows = []
    stats: dict[str, list[tuple[int, float, float]]] = {}
    for n in args.scans:
        subjects = -(-n // (1 + POSES))
        db = work / f"db{n}"
        stages = {
            "population-1-worker": (["population", "--subjects", str(subjects), "--poses", str(POSES), "--seed",
                                     "0", "--out", str(db), "--force", "--workers", "1"], db),
            "population": (["population", "--subjects", str(subjects), "--poses", str(POSES), "--seed", "0",
                            "--out", str(db), "--force"], db),
            "build-rre": (["build", str(db), "--out", str(work / f"rre{n}.npz"), "--selection", "all",
                           "--scratch", str(work), "--force"], work / f"rre{n}.npz"),
            "build-vertex": (["build", str(db), "--encoding", "vertex", "--out", str(work / f"vertex{n}.npz"),
                              "--selection", "all", "--scratch", str(work), "--force"], work / f"vertex{n}.npz"),
            "measure": (["measure", str(db), "--csv", str(work / f"m{n}.csv"), "--force"], work / f"m{n}.csv"),
            "measure-posed": (["measure", str(db), "--csv", str(work / f"p{n}.csv"), "--as-posed", "--force"],
                              work / f"p{n}.csv"),
        }
        for stage, (cli, output) in stages.items():
            if stage == "population-1-worker" and args.baseline_scans is not None and n not in args.baseline_scans:
                continue
            if stage in args.skip or (not stage.startswith("population") and not db.exists()):
                continue
            if output.is_file():
                output.unlink()  # CSV files carry no signature for --force
            load = os.getloadavg()[0]
            wall, cpu, pss, rss, said = _spawn_measured(cli)
            scans = subjects * (1 + POSES)
            rows.append((stage, scans, wall, cpu, pss, rss, disk_gb(output), load, said))
            stats.setdefault(stage, []).append((scans, wall, cpu, pss))
            print(f"| {stage} | {scans:,} | {wall:.1f} s | {cpu:.1f} s | {scans / wall:,.1f} scans/s | {pss:.2f} GB | "
                  f"{rss:.2f} GB | {disk_gb(output):.2f} GB | {load:.1f} | {said} |", flush=True)
            base = stats.get("population-1-worker", [(0,)])[-1]
            if stage == "population" and base[0] == scans:  # the baseline at this N
                report(f"population of {scans:,} scans (workers: one per core, against --workers 1)", wall, base[1],
                       scans, "scans")
    print("\n| work | scans | wall | CPU | rate (wall) | peak PSS | peak RSS (sum) | disk | load before | output |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for stage, scans, wall, cpu, pss, rss, disk, load, said in rows:
        print(f"| {stage} | {scans:,} | {wall:.1f} s | {cpu:.1f} s | {scans / wall:,.1f} scans/s | {pss:.2f} GB | "
              f"{rss:.2f} GB | {disk:.2f} GB | {load:.1f} | {said} |")
    print("\n| work | wall growth | CPU growth | peak memory growth |")
    print("|---|---|---|---|")
    for stage, points in stats.items():
        ns = [p[0] for p in points]
        print(f"| {stage} | {fitted_growth(ns, [p[1] for p in points])} | {fitted_growth(ns, [p[2] for p in points])} "
              f"| {fitted_growth(ns, [p[3] for p in points])} |")
    if "pca" not in args.skip and args.pca_scans:
        folder = work / f"db{args.pca_scans}"
        if folder.exists():
            pca_side_by_side(folder, work)
    print(f"\nthis process: peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GB")


if __name__ == "__main__":
    main()
