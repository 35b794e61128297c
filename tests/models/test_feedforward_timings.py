"""The feed-forward stage times its steps (wall and CPU seconds) into report.json, and they sum to the stage's
seconds (issue 40, item 1)."""

from __future__ import annotations

import json

import pytest

from ffrecon.cli import main


def test_the_feedforward_steps_sum_to_the_stage(small_demo, tmp_path):
    out = tmp_path / "out"
    args = ["run", str(small_demo.images), "-o", str(out), "--model", str(small_demo.model)]
    assert main([*args, "--no-colmap", "--no-refine", "--no-splat", "-q"]) == 0
    report = json.loads((out / "report.json").read_text())
    section, stage = report["feedforward"], report["timings"]["feedforward"]["seconds"]
    steps = {k: v for k, v in section["timings_s"].items() if k != "total"}
    assert {"load_model", "predict", "fuse", "write_sparse", "write_depth", "other"} <= set(steps)
    assert sum(steps.values()) == pytest.approx(stage, rel=0.05)
    assert section["cpu_s"]["predict"] > 0 and section["cpu_s"]["total"] > 0
