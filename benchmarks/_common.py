"""Shared helpers for the benchmarks: best-of-N timing, and the ratio line every benchmark prints."""

from __future__ import annotations

import time


def best_time(fn, repeat: int = 3, clock=time.perf_counter) -> float:
    """Best seconds of ``repeat`` calls (the machines are shared and noisy): wall clock, or
    ``clock=time.thread_time`` for the CPU seconds of the calling thread."""
    best = float("inf")
    for _ in range(repeat):
        t = clock()
        fn()
        best = min(best, clock() - t)
    return best


def report(name: str, fast_s: float, baseline_s: float, unit_count: int, unit: str) -> None:
    """Print rates for a fast path and its baseline measured in the same process, and their ratio."""
    print(f"{name}: {unit_count / fast_s:,.0f} {unit}/s (baseline {unit_count / baseline_s:,.0f} {unit}/s), "
          f"speed-up x{baseline_s / fast_s:.1f}")
