"""Is the population's remaining time honest? (issue 16) The estimate the progress bar shows
(``cli.common.remaining_seconds``: the run's rate since its first report) at each tenth of the
work, against the time the run then really took to finish; and the run's peak memory, the
parent and its worker processes together (``_treemem``).

    PYTHONPATH=src python benchmarks/bench_population_eta.py --subjects 10000 --poses 10 --out /tmp/pop
    PYTHONPATH=src python benchmarks/bench_population_eta.py --log /tmp/pop.progress.jsonl   # a past run

The run writes ``OUT.progress.jsonl`` (seconds since the start, fraction, message per report);
``--log`` evaluates such a file without running anything. The output is large (about 160 kB a
scan): delete it afterwards.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _treemem import TreeMemory  # noqa: E402

from bodyspace.cli.common import remaining_seconds  # noqa: E402


def evaluate(samples: list[tuple[float, float, str]]) -> None:
    """Print, near each tenth of the work, the remaining time shown and the time really left."""
    end = samples[-1][0]
    first = samples[0][:2]
    print("| done | elapsed | remaining shown | remaining really | shown / real |")
    print("|---|---|---|---|---|")
    ratios = []
    for tenth in range(1, 10):
        t, f, _ = min(samples, key=lambda s: abs(s[1] - tenth / 10))
        shown = remaining_seconds(first, (t, f))
        real = end - t
        if shown is None or real <= 0:
            continue
        ratios.append(shown / real)
        print(f"| {100 * f:.0f} % | {t:,.0f} s | {shown:,.0f} s | {real:,.0f} s | {shown / real:.2f} |")
    last = max((s for s in samples if s[1] < 1.0), key=lambda s: s[1])  # the last report before "done"
    shown = remaining_seconds(first, last[:2])
    if shown is not None and end > last[0]:
        ratios.append(shown / (end - last[0]))
        print(f"| {100 * last[1]:.0f} % ({last[2]}) | {last[0]:,.0f} s | {shown:,.0f} s | {end - last[0]:,.0f} s | "
              f"{shown / (end - last[0]):.2f} |")
    if ratios:
        print(f"remaining time shown / real: {min(ratios):.2f} .. {max(ratios):.2f} (1 = exact), over {end:,.0f} s")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--subjects", type=int, default=2000)
    parser.add_argument("--poses", type=int, default=10)
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--out", type=Path, default=Path("/tmp/bench-population-eta"))
    parser.add_argument("--log", type=Path, default=None, help="evaluate this progress log of a past run instead")
    args = parser.parse_args()
    if args.log is not None:
        evaluate([tuple(json.loads(line)) for line in args.log.read_text().splitlines()])
        return
    from bodyspace.data.template import load_template
    from bodyspace.synth.population import build_population

    print(f"bench_population_eta: {args.subjects} subjects x (1 + {args.poses}) scans, {os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.1f}", flush=True)
    template = load_template()
    log_path = args.out.with_name(args.out.name + ".progress.jsonl")
    samples = []
    t0 = time.perf_counter()
    with open(log_path, "w") as log, TreeMemory(os.getpid()) as memory:
        def progress(message: str, fraction: float) -> None:
            samples.append((time.perf_counter() - t0, fraction, message))
            log.write(json.dumps(samples[-1]) + "\n")
            log.flush()

        db = build_population(template, args.out, args.subjects, args.poses, rng=0, progress=progress,
                              workers=args.workers, overwrite=True, log=print)
    wall = time.perf_counter() - t0
    print(f"{db.n_scans:,} scans in {wall:,.0f} s ({db.n_scans / wall:,.1f} scans/s), load average now "
          f"{os.getloadavg()[0]:.1f}; peak memory of the process tree: PSS {memory.peak_pss_gb:.2f} GiB, "
          f"RSS summed {memory.peak_rss_gb:.2f} GiB ({memory.peak_processes} processes)")
    evaluate(samples)
    shutil.rmtree(args.out)


if __name__ == "__main__":
    main()
