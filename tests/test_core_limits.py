"""The cores work may use are the process's CPU affinity (taskset, a container's cpuset), not the machine's."""

from __future__ import annotations

import os

import pytest

from ffrecon.concurrency import CoreShare, available_cores


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
