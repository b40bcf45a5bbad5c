"""Two lanes for one body: run two halves of a compiled kernel's work side by side.

Batches already use both cores by decoding bodies on threads (``RelativeRotationEncoder``'s
``n_jobs``). A single body has no such parallelism, yet latency matters most there (one
interactive decode, one step of a closed loop). Its kernels (numba, ``nogil``) are split in
two and the second half runs on one persistent worker thread while the calling thread runs
the first. numba's own ``parallel=True`` was not used: its default threading layer
(workqueue) aborts when two Python threads launch parallel kernels at once, which is exactly
what a threaded batch does.

Callers ask for two lanes only for a single body; a batch keeps one lane per thread.
"""

from __future__ import annotations

import atexit
import threading
from concurrent.futures import ThreadPoolExecutor

_pool: ThreadPoolExecutor | None = None
_lock = threading.Lock()


def _worker() -> ThreadPoolExecutor:
    global _pool
    if _pool is None:
        with _lock:
            if _pool is None:
                _pool = ThreadPoolExecutor(1, thread_name_prefix="bodyspace-lane")
                atexit.register(_pool.shutdown, wait=False)
    return _pool


def run_both(first, second):
    """Call ``first()`` here and ``second()`` on the worker thread; return both results.

    The worker is shared by every caller: two threads calling ``run_both`` at once queue on
    it (correct, only not faster), which is why batches should not ask for lanes. ``second``
    must not call ``run_both`` itself (it would wait for the worker it runs on).
    """
    future = _worker().submit(second)
    try:
        a = first()
    finally:
        b = future.result()
    return a, b


def halves(n: int) -> tuple[tuple[int, int], tuple[int, int]]:
    """The ranges ``(0, m), (m, n)`` splitting ``n`` items into two nearly equal parts."""
    m = n // 2
    return (0, m), (m, n)
