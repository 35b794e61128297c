"""tools/bench_run.py says where a run's "other" seconds (wall no stage of report.json holds) went (issue 40,
item 1): the imports, the report, the interpreter's start and exit, and what is left between the stages."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

TOOL = Path(__file__).resolve().parents[1] / "tools" / "bench_run.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_run_other", TOOL)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_other_seconds_are_split_into_their_parts_and_sum_to_other(bench):
    stats = {"first": [2.9, 2.8], "last": [60.8, 76.0], "end": [63.2, 78.4]}
    parts = bench.other_parts(stats, other_s=7.05, wall=64.8)
    assert parts["imports+parse"] == pytest.approx(2.9)
    assert parts["report+summary"] == pytest.approx(2.4)
    assert parts["start+exit"] == pytest.approx(1.6)
    assert sum(parts.values()) == pytest.approx(7.05)
    assert bench.other_parts({}, 1.0, 2.0) == {}  # a child that recorded nothing: no parts
