"""Peak memory of a process and all its descendants together (Linux /proc), sampled.

``ru_maxrss`` (and ``/usr/bin/time -v``) reports the largest *single* process: a run that
forks workers is larger than that. ``TreeMemory`` samples, every ``interval`` seconds, the sum
over the process tree of the resident size (RSS: pages shared after a fork counted once per
process, an upper bound) and of the proportional set size (PSS: shared pages split between the
processes sharing them, what the tree really costs the machine), and keeps the peaks.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path


def _tree(root: int) -> list[int]:
    pids, todo = [], [root]
    while todo:
        pid = todo.pop()
        pids.append(pid)
        try:
            for task in Path(f"/proc/{pid}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass
    return pids


def _rss_pss_kb(pid: int) -> tuple[int, int]:
    rss = pss = 0
    try:
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            if line.startswith("Rss:"):
                rss = int(line.split()[1])
            elif line.startswith("Pss:"):
                pss = int(line.split()[1])
    except OSError:
        pass
    return rss, pss


class TreeMemory:
    """``with TreeMemory(pid) as m: ...``; then ``m.peak_rss_gb``, ``m.peak_pss_gb`` (GiB, sums over
    the tree at the sampled instant of its peak) and ``m.peak_processes``."""

    def __init__(self, pid: int, interval: float = 0.5):
        self.pid, self.interval = pid, interval
        self.peak_rss_kb = self.peak_pss_kb = self.peak_processes = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            pids = _tree(self.pid)
            sizes = [_rss_pss_kb(p) for p in pids]
            self.peak_rss_kb = max(self.peak_rss_kb, sum(s[0] for s in sizes))
            self.peak_pss_kb = max(self.peak_pss_kb, sum(s[1] for s in sizes))
            self.peak_processes = max(self.peak_processes, len(pids))
            self._stop.wait(self.interval)

    def __enter__(self) -> "TreeMemory":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    @property
    def peak_rss_gb(self) -> float:
        return self.peak_rss_kb / 2**20

    @property
    def peak_pss_gb(self) -> float:
        return self.peak_pss_kb / 2**20


if __name__ == "__main__":  # python _treemem.py PID: sample until PID exits, print the peaks
    import sys

    pid = int(sys.argv[1])
    with TreeMemory(pid) as m:
        while os.path.exists(f"/proc/{pid}"):
            time.sleep(0.5)
    print(f"peak tree RSS {m.peak_rss_gb:.2f} GiB, peak tree PSS {m.peak_pss_gb:.2f} GiB, "
          f"processes {m.peak_processes}")
