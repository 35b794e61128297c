"""tools/bench_run.py's accounting (issue 40): CPU seconds by step of the plan, ratios to COLMAP alone with and
without the network's calls, thread scaling between CPU lists."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

TOOL = Path(__file__).resolve().parents[1] / "tools" / "bench_run.py"
FAST = ["--no-colmap", "--no-refine", "--no-splat", "-q"]


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_run", TOOL)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_cpu_by_step_names_the_stages_that_ran_and_joins_those_side_by_side(bench):
    stats = {
        "steps": [
            {"stages": ["capture"], "wall_s": 1.0, "cpu_s": 0.9},
            {"stages": ["feedforward", "colmap", "sift"], "wall_s": 5.0, "cpu_s": 9.0},
            {"stages": ["splat"], "wall_s": 0.0, "cpu_s": 0.0},  # skipped: not in report.json's timings
        ],
        "first": [3.0, 2.5],
        "last": [7.0, 12.5],
        "end": [8.5, 13.7],
        "inference": {"calls": 2, "wall_s": 1.5, "cpu_s": 2.0},
    }
    out = bench.stage_cpu(stats, ran={"capture", "feedforward", "sift"})
    assert out["cpu"] == {"capture": 0.9, "feedforward+sift": 9.0}
    assert out["wall"] == {"capture": 1.0, "feedforward+sift": 5.0}
    assert out["before"] == (3.0, 2.5) and out["after"] == pytest.approx((1.5, 1.2))
    assert out["inference"]["calls"] == 2


def test_ratios_to_colmap_alone_in_wall_and_cpu_with_and_without_the_network(bench):
    rows = [
        {"method": "COLMAP alone", "wall_s": 20.0, "cpu_s": 30.0, "stages": {"colmap": 19.0}},
        {
            "method": "ffrecon quick",
            "wall_s": 10.0,
            "cpu_s": 15.0,
            "stages": {"feedforward": 4.0, "refine": 2.0},
            "by_step": {"inference": {"wall_s": 2.0, "cpu_s": 3.0}},
        },
    ]
    bench.compare_with_colmap(rows)
    quick = rows[1]
    assert quick["ratio"] == 0.5 and quick["cpu_ratio"] == 0.5
    assert quick["ex_inference"] == {"wall_s": 8.0, "cpu_s": 12.0, "ratio": 0.4, "cpu_ratio": 0.4}
    assert quick["pose_s"] == 6.0 and quick["pose_speedup"] == pytest.approx(19.0 / 6.0)
    assert rows[0]["ratio"] == 1.0


def test_thread_scaling_compares_the_first_and_last_cpu_lists_per_mode(bench):
    rows = [
        {"mode": "colmap", "cpus": "0", "wall_s": 30.0, "stages": {"colmap": 29.0}},
        {"mode": "colmap", "cpus": "0,1", "wall_s": 17.0, "stages": {"colmap": 16.0}},
        {"mode": "quick", "cpus": "0", "wall_s": 9.0, "stages": {"refine": 1.5}, "steps": {"refine matching": 2.2}},
        {"mode": "quick", "cpus": "0,1", "wall_s": 6.0, "stages": {"refine": 1.0}, "steps": {"refine matching": 1.1}},
    ]
    assert bench.scaling(rows) == [
        ("colmap", "wall", 30.0, 17.0),
        ("colmap", "colmap", 29.0, 16.0),
        ("quick", "wall", 9.0, 6.0),
        ("quick", "refine matching", 2.2, 1.1),  # refine itself took under 2 s on both: left out
    ]
    assert bench.scaling(rows[:1] + rows[2:3]) == []  # one CPU list: nothing to compare


def test_the_ffrecon_child_runs_the_command_and_records_each_stage(bench, small_demo, tmp_path):
    from ffrecon.models import runner
    from ffrecon.state import StagePlan

    plan_run, model_run = StagePlan.run, runner.OnnxModel.run
    stats = tmp_path / "stats.json"
    run = ["run", str(small_demo.images), "-o", str(tmp_path / "out"), "--model", str(small_demo.model), *FAST]
    assert bench.main(["--ffrecon-child", str(stats), "--", *run]) == 0
    recorded = json.loads(stats.read_text())
    steps = {"+".join(s["stages"]): s for s in recorded["steps"]}
    assert steps["capture"]["cpu_s"] > 0 and steps["capture"]["wall_s"] > 0
    assert next(s for name, s in steps.items() if name.startswith("feedforward"))["cpu_s"] > 0
    assert recorded["inference"]["calls"] >= 1 and recorded["inference"]["wall_s"] > 0
    assert recorded["first"][0] <= recorded["last"][0] <= recorded["end"][0]
    assert (StagePlan.run, runner.OnnxModel.run) == (plan_run, model_run)  # the wrapping is undone


def test_the_splat_budget_goes_only_to_runs_that_make_a_splat(bench, tmp_path):
    args = bench._parser().parse_args(["--no-splat", "--splat-seconds", "30"])
    command = {
        mode: bench.ffrecon_command(tmp_path, tmp_path / "m.onnx", tmp_path / "out", tmp_path / "gt", mode, args)
        for mode in ("quick", "default+splat")
    }
    run = command["quick"][command["quick"].index("--") + 1 :]
    assert run[0] == "run" and "--quick" in run and "--no-splat" in run and "--splat-seconds" not in run
    with_splat = command["default+splat"]
    assert "--no-splat" not in with_splat and with_splat[with_splat.index("--splat-seconds") + 1] == "30.0"
    assert "--quick" not in with_splat


# Where a run's "other" seconds (wall no stage of report.json holds) went (issue 40, item 1).
def test_other_seconds_are_split_into_their_parts_and_sum_to_other(bench):
    stats = {"first": [2.9, 2.8], "last": [60.8, 76.0], "end": [63.2, 78.4]}
    parts = bench.other_parts(stats, other_s=7.05, wall=64.8)
    assert parts["imports+parse"] == pytest.approx(2.9)
    assert parts["report+summary"] == pytest.approx(2.4)
    assert parts["start+exit"] == pytest.approx(1.6)
    assert sum(parts.values()) == pytest.approx(7.05)
    assert bench.other_parts({}, 1.0, 2.0) == {}  # a child that recorded nothing: no parts


def test_other_seconds_once_the_report_times_the_runs_own_startup_and_report(bench):
    """With report.json's "startup" and "report" owned, "other" is split into what follows the report's entry, the
    gaps between stages and the process's start and exit; the parts still sum to "other"."""
    stats = {"first": [2.9, 2.8], "last": [60.8, 76.0], "end": [61.0, 76.1]}
    timings = {"startup": 3.3, "capture": 10.0, "feedforward": 47.7, "report": 0.15}
    report = {"timings": {k: {"seconds": v} for k, v in timings.items()}, "concurrent_stages": []}
    wall = 61.5
    other = wall - bench.stages_wall(report)
    parts = bench.other_parts(stats, other_s=other, wall=wall, report=report)
    assert parts["after the report"] == pytest.approx(0.05)
    assert parts["between stages"] == pytest.approx(0.2)
    assert sum(parts.values()) == pytest.approx(other) and "imports+parse" not in parts
