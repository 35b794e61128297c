"""Quick mode (--quick): the model's cameras refined by bundle adjustment, no COLMAP reconstruction."""

import json

import pytest

from ffrecon.cli import main
from ffrecon.errors import InputError
from ffrecon.pipeline import RunOptions, run
from ffrecon.results import QUICK_NO_CROSSCHECK, QUICK_STATEMENT, RunMode
from ffrecon.sfm.refine.options import RefineOptions
from ffrecon.workspace import staging_path


def test_quick_mode_reaches_ground_truth_accuracy_and_says_nothing_checked_it(demo12, tmp_path, capsys):
    """The demo12 scene (12 frames 320x240, one frame 20 deg off in the simulated model) through the command line."""
    out = tmp_path / "out"
    scene = ["--frames", "12", "--width", "320", "--height", "240", "--seed", "1"]  # demo12's scene, cached
    assert main(["demo", *scene, "-o", str(out), "--quick", "--no-splat"]) == 0
    assert QUICK_STATEMENT in capsys.readouterr().out  # the end-of-run summary
    report = json.loads((out / "report.json").read_text())
    assert report["mode"] == "quick" and report["cross_check_note"] == QUICK_STATEMENT
    assert QUICK_STATEMENT in (out / "report.html").read_text()
    # No COLMAP reconstruction: the gates that need one are skipped, saying why, and nothing failed.
    assert report["colmap"] == {"skipped": QUICK_NO_CROSSCHECK} and not (out / "crosscheck").exists()
    verdicts = {g["name"]: g for g in report["gates"] + report["evidence"]["gates"]}
    for name in ("registration", "sparse_cloud", "colmap_agreement"):
        assert verdicts[name]["status"] == "skipped" and QUICK_NO_CROSSCHECK in verdicts[name]["reason"], name
    assert all(v["status"] != "fail" for v in verdicts.values())
    # Every frame refined; the model's one badly wrong frame is moved far by its matches: corrected.
    counts = {k: v for k, v in report["evidence"]["counts"].items() if v}
    assert counts == {"refined on image matches": 11, "corrected by the evidence": 1}
    assert len(report["evidence"]["verdicts"]["confirmed"]) == 11 and not report["evidence"]["verdicts"]["unchecked"]
    # The refinement extracted its own SIFT and matched only the pairs the model says overlap.
    refine = report["refine"]
    assert refine["timings_s"]["feature_extraction"] > 0 and refine["num_pairs_matched"] < 12 * 11 // 2
    # Against ground truth: as accurate as the default mode's refined cameras (tests/sfm/test_refine.py).
    metrics = report["pose_errors"]["refined_vs_ground_truth"]["metrics"]
    assert metrics["num_registered"] == 12
    assert metrics["AUC@5"] >= 0.98 and metrics["median_rotation_deg"] <= 0.1, metrics
    assert report["pose_errors"]["feedforward_vs_ground_truth"]["metrics"]["median_rotation_deg"] > 1.0
    assert report["exports"]["cameras"] == "refined"


def test_quick_mode_needs_a_model_and_the_refinement(demo12, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["run", str(demo12.images), "-o", str(out), "--quick", "-q"]) == 2
    err = capsys.readouterr().err
    assert "quick mode (--quick) refines a model's cameras, and no model was given" in err
    assert "fix: pass --model" in err
    assert not out.exists() and not staging_path(out.resolve()).exists()  # refused before any work
    model = ["--model", str(demo12.model)]
    assert main(["run", str(demo12.images), "-o", str(out), *model, "--quick", "--no-refine", "-q"]) == 2
    assert "--no-refine" in capsys.readouterr().err and not out.exists()
    with pytest.raises(InputError, match="no model was given"):
        run(demo12.images, out, None, RunOptions.quick())


def test_quick_preset():
    options = RunOptions.quick(force=True)
    assert options.mode is RunMode.QUICK and options.force and not options.colmap.enabled
    assert options.refine == RefineOptions.quick() and options.refine.sift.first_octave == 0
    assert RunOptions().mode is RunMode.FULL and RunOptions().colmap.enabled
