"""Issue 25: each stage's peak memory in the timings (report.json ``timings.<stage>.peak_rss_gb``)."""

import numpy as np
import pytest

from ffrecon.machine import reset_peak_rss
from ffrecon.resume import StageRunner


def _allocate(megabytes: int):
    def stage():
        block = np.ones(megabytes * 2**20, np.uint8)  # touched, so resident
        return int(block[::4096].sum() > 0)

    return stage


def test_each_stage_reports_its_own_peak(tmp_path):
    if not reset_peak_rss():
        pytest.skip("this kernel does not let a process reset its memory high-water mark")
    runner = StageRunner(tmp_path, reuse=True)
    runner.run("big", _allocate(400), options=(), inputs=[])
    runner.run("small", _allocate(10), options=(), inputs=[])
    runner.run("big", _allocate(400), options=(), inputs=[])  # reused: nothing ran, nothing measured
    big, small, reused = runner.timings
    assert big.peak_rss_gb - small.peak_rss_gb >= 0.35, "the mark was reset between the stages"
    assert reused.reused and reused.peak_rss_gb is None


def test_the_second_of_two_stages_side_by_side_leaves_the_measure_to_the_first(tmp_path):
    runner = StageRunner(tmp_path, reuse=False)
    with runner.side_by_side() as beside:
        beside.run("second", _allocate(10), options=(), inputs=[])
    assert runner.timings[0].stage == "second" and runner.timings[0].peak_rss_gb is None
