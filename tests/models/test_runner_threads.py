"""The ONNX runner's CPU threads follow the cores this process may run on (taskset, a container's cpuset), not
the machine's core count (issue 40)."""

from __future__ import annotations

import os

import pytest

from ffrecon.models import runner


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="no CPU affinity on this system")
def test_cpu_threads_follow_the_affinity(monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0})  # as under taskset -c 0
    monkeypatch.setattr(os, "cpu_count", lambda: 16)
    assert runner.cpu_threads(0, use_cuda=False) == 1
    assert runner.cpu_threads(3, use_cuda=False) == 3  # asked for: as asked
