"""Two lanes for one body: run two halves of a compiled kernel's work side by side.

Batches already use both cores by decoding bodies on threads (``RelativeRotationEncoder``'s
``n_jobs``). A single body has no such parallelism, yet latency matters most there (one
interactive decode, one step of a closed loop). Its kernels (numba, ``nogil``) are split in
two and the second half runs on one persistent worker thread while the calling thread runs
the first. numba's own ``parallel=True`` was not used: its default threading layer
(workqueue) aborts when two Python threads launch parallel kernels at once, which is exactly
what a threaded batch does.

Callers ask for two lanes only for a single body; a batch keeps one lane per thread.

Long streamed jobs made of independent chunks (a population) use both cores with processes
instead: ``in_order`` runs a chunk function in forked worker processes and yields the results
in chunk order. Each worker is one lane (``run_both`` runs both halves in turn there), so two
workers keep two cores busy without four threads fighting for them.
"""

from __future__ import annotations

import atexit
import ctypes
import multiprocessing
import os
import signal
import threading
from collections import deque
from contextlib import contextmanager
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Callable, Iterable, Iterator

from threadpoolctl import threadpool_limits

from bodyspace.errors import BodyspaceError

_pool: ThreadPoolExecutor | None = None
_lock = threading.Lock()
_one_lane = False  # set in in_order's workers: a process that is one of several runs one lane


def _forget_worker_thread() -> None:
    """After a fork: the parent's lane thread does not exist in the child, so an inherited pool
    would take work it never runs (the child would wait forever); the child makes its own."""
    global _pool, _lock
    _pool, _lock = None, threading.Lock()


os.register_at_fork(after_in_child=_forget_worker_thread)


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
    if _one_lane:
        return first(), second()
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


def cores() -> int:
    """The cores this process may run on (its affinity mask, not the machine's count)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def _start_worker(parent: int) -> None:
    """Initializer of ``in_order``'s processes: one lane, one BLAS thread, die with the parent.

    Without PR_SET_PDEATHSIG a parent killed with SIGKILL leaves its workers waiting forever on
    their task queue (and a chunk still being written by an orphan). SIGINT is ignored: Ctrl-C
    reaches the whole process group, and the parent, not each worker, decides what stops.
    """
    global _one_lane
    _one_lane = True
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG (Linux)
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent:  # the parent died before the line above took effect
        os._exit(1)
    threadpool_limits(1, user_api="blas")


def in_order(fn: Callable, tasks: Iterable[tuple], workers: int, ahead: int = 2,
             died: str = "run the same command again") -> Iterator:
    """``fn(*task)`` for each task, yielded in the tasks' order.

    ``workers`` > 1: in that many forked processes, at most ``ahead`` tasks each in flight, so
    memory is bounded and ``tasks`` (an iterator) is consumed in order, a few tasks ahead of the
    results. ``fn`` and what it reads are inherited at the fork, so only the task's arguments
    and the result cross the process boundary: keep both small (a chunk's rows go to disk from
    the worker). The results must not depend on which process computed them (the caller's
    contract; ``fn`` runs with one BLAS thread everywhere, here included, so a chunk's
    floating-point work is the same whatever the number of workers; ``run_both``'s two lanes
    compute the same halves either way).
    ``workers`` <= 1 (or inside a daemon process, which may not fork): here, one task at a time.
    A worker that dies (killed, out of memory) raises a BodyspaceError ending in ``died`` (what
    the user should do about it).
    """
    tasks = iter(tasks)
    if workers <= 1 or multiprocessing.current_process().daemon:
        for task in tasks:
            with threadpool_limits(1, user_api="blas"):
                result = fn(*task)
            yield result
        return
    with _forked_executor(workers) as pool:
        queue = deque(pool.submit(fn, *task) for _, task in zip(range(workers * ahead), tasks))
        while queue:
            try:
                result = queue.popleft().result()
            except BrokenProcessPool:
                raise BodyspaceError(f"a worker process died (killed, or out of memory); {died}") from None
            following = next(tasks, None)
            if following is not None:
                queue.append(pool.submit(fn, *following))
            yield result


@contextmanager
def _forked_executor(workers: int):
    """A pool of ``workers`` forked one-lane processes (``_start_worker``) for the block. Ended by
    an exception (Ctrl-C, an error, a generator closed early), its processes are killed: the tasks
    in flight are abandoned, not awaited (a resumed run computes them again)."""
    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork"),
                               initializer=_start_worker, initargs=(os.getpid(),))
    finished = False
    try:
        yield pool
        finished = True
    finally:
        if not finished:
            for process in list(getattr(pool, "_processes", {}).values()):
                process.kill()
        pool.shutdown(wait=True, cancel_futures=True)


@contextmanager
def forked_pool(workers: int, died: str = "run the same command again"):
    """Up to ``workers`` forked processes kept for several rounds of independent tasks; yields
    ``run(fn, tasks) -> list``: ``fn(*task)`` for each task, the results in the tasks' order.

    For a few short tasks in a row (a registration's start fits: 0.1-0.3 s each, in rounds that
    depend on the last) where ``in_order``'s pool per call would fork each round. The processes
    are forked at the first tasks that need them, so what ``fn`` reads must be in place before the
    first ``run`` and unchanged until the block ends; each is one lane with one BLAS thread and
    dies with the parent, as ``in_order``'s. ``workers`` <= 1, inside a daemon process, or inside
    one of ``in_order``'s workers (already one of several processes): the tasks run here, one at a
    time, with one BLAS thread (the same results).
    """
    if workers <= 1 or _one_lane or multiprocessing.current_process().daemon:
        def here(fn: Callable, tasks: Iterable[tuple]) -> list:
            with threadpool_limits(1, user_api="blas"):
                return [fn(*task) for task in tasks]
        yield here
        return
    with _forked_executor(workers) as pool:
        def run(fn: Callable, tasks: Iterable[tuple]) -> list:
            futures = [pool.submit(fn, *task) for task in tasks]
            try:
                return [f.result() for f in futures]
            except BrokenProcessPool:
                raise BodyspaceError(f"a worker process died (killed, or out of memory); {died}") from None

        yield run
