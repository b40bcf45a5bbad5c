"""bodyspace.parallel.in_order: results in task order from forked workers, errors and deaths
brought back to the caller, no worker left behind."""

import os
import signal

import pytest

from bodyspace import parallel
from bodyspace.errors import BodyspaceError, ParameterError


def _square_or_fail(i):
    if i == 5:
        raise ParameterError("task 5 is refused")
    return i * i, os.getpid()


def _die(i):
    if i == 2:
        os.kill(os.getpid(), signal.SIGKILL)
    return i


def test_in_order_keeps_task_order_and_uses_workers():
    done = list(parallel.in_order(_square_or_fail, ((i,) for i in range(5)), workers=2))
    assert [r[0] for r in done] == [0, 1, 4, 9, 16]
    assert os.getpid() not in {r[1] for r in done}
    # One worker (or fewer): here, in order.
    assert [r[1] for r in parallel.in_order(_square_or_fail, [(1,), (2,)], workers=1)] == [os.getpid()] * 2


def test_in_order_raises_a_workers_error_and_a_dead_worker():
    with pytest.raises(ParameterError, match="task 5 is refused"):
        list(parallel.in_order(_square_or_fail, ((i,) for i in range(8)), workers=2))
    with pytest.raises(BodyspaceError, match="a worker process died.*run it again"):
        list(parallel.in_order(_die, ((i,) for i in range(6)), workers=2, died="run it again"))


_SHARED = {}


def _shared_times(i):
    return _SHARED["factor"] * i, os.getpid()


def test_forked_pool_keeps_its_workers_across_rounds_and_reads_what_was_set_before():
    """parallel.forked_pool: several rounds on the same forked workers, results in task order,
    the parent's module state as it was at the fork; a worker's error and death come back."""
    _SHARED["factor"] = 3
    with parallel.forked_pool(2) as run:
        first = run(_shared_times, [(i,) for i in range(4)])
        second = run(_shared_times, [(i,) for i in range(4, 6)])
    assert [r[0] for r in first + second] == [0, 3, 6, 9, 12, 15]
    pids = {r[1] for r in first + second}
    assert os.getpid() not in pids and len(pids) <= 2
    with parallel.forked_pool(1) as run:               # one worker: here
        assert {r[1] for r in run(_shared_times, [(1,), (2,)])} == {os.getpid()}
    with pytest.raises(ParameterError, match="task 5 is refused"), parallel.forked_pool(2) as run:
        run(_square_or_fail, [(i,) for i in range(8)])
    with pytest.raises(BodyspaceError, match="a worker process died.*again"), parallel.forked_pool(2, "again") as run:
        run(_die, [(i,) for i in range(6)])
