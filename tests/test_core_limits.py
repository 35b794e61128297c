"""How many threads a run's work uses: the cores of the process's CPU affinity (taskset, a container's cpuset), not
the machine's; numpy's OpenBLAS on one thread while a run lasts (its products are tall and thin, issue 40)."""

from __future__ import annotations

import os

import numpy as np
import pytest

from ffrecon import pipeline
from ffrecon.concurrency import CoreShare, available_cores, blas_threads, numpy_openblas
from ffrecon.errors import InputError


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="no CPU affinity on this system")
def test_the_cores_are_those_the_process_may_run_on(monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0})
    monkeypatch.setattr(os, "cpu_count", lambda: 16)
    assert available_cores() == 1
    cores = CoreShare()
    assert cores.cores == 1
    with cores.claim(1):
        assert cores.step() == 1  # still one thread for the work beside, never none


def test_given_cores_are_kept():
    assert CoreShare(3).cores == 3


needs_openblas = pytest.mark.skipif(numpy_openblas() is None, reason="numpy's BLAS is not a known OpenBLAS")


@needs_openblas
def test_blas_threads_holds_numpys_openblas_for_the_block_and_restores_it():
    set_threads, get_threads = numpy_openblas()
    before = get_threads()
    set_threads(2)
    try:
        with blas_threads(1):
            assert get_threads() == 1
            a = np.arange(12.0).reshape(4, 3)
            assert np.array_equal(a @ np.eye(3), a)  # products still work
        assert get_threads() == 2
    finally:
        set_threads(before)


@needs_openblas
def test_a_run_holds_one_blas_thread_while_it_lasts(monkeypatch, tmp_path):
    set_threads, get_threads = numpy_openblas()
    before, seen = get_threads(), []
    set_threads(2)  # as on a machine of two cores or more, where the run's one thread differs

    def stages(*args):
        seen.append(get_threads())
        raise InputError("stopped here", "nothing to fix")

    monkeypatch.setattr(pipeline, "_run_stages", stages)
    (tmp_path / "photos").mkdir()
    try:
        with pytest.raises(InputError, match="stopped here"):
            pipeline.run(tmp_path / "photos", tmp_path / "out", None)
        assert seen == [1] and get_threads() == 2
    finally:
        set_threads(before)


@pytest.mark.parametrize("workers", [1, 3])
def test_map_in_order_keeps_the_order_bounds_what_is_drawn_ahead_and_raises_in_place(workers):
    """Results in the items' order whatever order the threads finish in; the items drawn at most ``window`` ahead
    of the results taken; an error raised where its result would have come (issue 40: the capture measures and
    writes its frames on the cores while the next are decoded)."""
    import threading
    import time

    from ffrecon.concurrency import map_in_order

    drawn, threads = [], set()

    def items():
        for k in range(12):
            drawn.append(k)
            yield k

    def slow(k):
        threads.add(threading.current_thread().name)
        time.sleep(0.02 * ((7 * k) % 5))  # finishing out of order
        return k * k

    out = []
    for value in map_in_order(slow, items(), workers, window=4):
        out.append(value)
        assert len(drawn) - len(out) <= 4
    assert out == [k * k for k in range(12)]
    assert (len(threads) > 1) == (workers > 1)

    def failing(k):
        if k == 5:
            raise ValueError("five")
        return k

    got = []
    with pytest.raises(ValueError, match="five"):
        for value in map_in_order(failing, range(10), workers):
            got.append(value)
    assert got == [0, 1, 2, 3, 4]
