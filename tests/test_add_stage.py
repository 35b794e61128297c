"""Adding a stage is one module and one line in the stage list (issue 41; docs/architecture.md, "How to add a
stage"): a tiny stage, written here and added to a copy of :data:`ffrecon.stages.STAGES`, runs in order, is
recorded and reused on resume, and shows in the run's results, report.json and report.html, and one that skips
is listed among the skipped stages, with no other file edited."""

from __future__ import annotations

import dataclasses
import json

from ffrecon.pipeline import RunOptions, run
from ffrecon.sfm.crosscheck.options import ColmapOptions
from ffrecon.sfm.refine.options import RefineOptions
from ffrecon.splat.stage import SplatOptions
from ffrecon.stages import STAGES
from ffrecon.state import Share, Stage, StateView

FF_ONLY = dict(
    colmap=ColmapOptions(enabled=False), refine=RefineOptions(enabled=False), splat=SplatOptions(enabled=False)
)


# -- the one module: the stage, its result and its report section -------------------------------------------
def count_frames(state: StateView, options: RunOptions, share: Share) -> dict:
    """The tiny stage's work: how many frames, and how many the capture checks flagged."""
    flagged = {f.name for f in state.capture.quality.flags}
    return {"frames": state.views, "flagged": len(flagged)}


def frames_section(report: dict, run_dir) -> tuple[list[dict], str]:
    return [{"item": k, "value": v} for k, v in report["frame_count"].items()], ""


FRAME_COUNT = Stage(
    "frame_count",
    ("capture",),
    count_frames,
    lambda options: (),
    label="frame count",
    page=(("Frames counted", frames_section),),
)
NEVER = Stage("never", (), lambda s, o, c: 0, lambda o: (), label="never", skip=lambda s, o: "not today")

# -- the one line: the stage list with them -------------------------------------------------------------------
WITH_TINY = (*STAGES, FRAME_COUNT, NEVER)


def test_a_stage_added_to_the_list_runs_and_reports_with_no_other_file_edited(small_demo, tmp_path):
    out = tmp_path / "out"
    result = run(small_demo.images, out, small_demo.model, RunOptions(**FF_ONLY), stages=WITH_TINY)
    assert result.exit_code == 0
    report = json.loads((out / "report.json").read_text())
    counted = {"frames": 8, "flagged": len({f["name"] for f in report["inputs"]["quality"]["flags"]})}
    assert result["frame_count"] == counted and result["never"].reason == "not today"
    assert report["frame_count"] == counted and report["never"] == {"skipped": "not today"}
    assert {"stage": "never", "reason": "not today"} in report["skipped_stages"]
    assert list(report["timings"])[-2:] == ["frame_count", "report"]  # recorded and timed, after the other stages
    assert "<h2>Frames counted</h2>" in (out / "report.html").read_text()
    # Its record makes it resumable like the others: reused, with the same result.
    again = run(small_demo.images, out, small_demo.model, RunOptions(**FF_ONLY, resume=True), stages=WITH_TINY)
    assert {t.stage: t.reused for t in again.timings}["frame_count"] and again["frame_count"] == result["frame_count"]
    # Without it, nothing of it is left in the report.
    plain = run(small_demo.images, out, small_demo.model, dataclasses.replace(RunOptions(**FF_ONLY), resume=True))
    assert plain["frame_count"] is None and "frame_count" not in json.loads((out / "report.json").read_text())
