"""run(...) chains the stages: Capture -> Pose (feed-forward, COLMAP) -> Refine -> Splat -> Export/Report."""

from __future__ import annotations

import datetime as dt
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

from ffrecon import __version__
from ffrecon.capture import CaptureOptions, run_capture
from ffrecon.export.nerfstudio import write_transforms
from ffrecon.export.pointcloud import write_point_cloud
from ffrecon.export.report import ReportBuilder
from ffrecon.models.stage import FeedForwardOptions, run_feedforward
from ffrecon.report_sections import add_capture, add_feedforward, finish_report
from ffrecon.workspace import staged_output

log = logging.getLogger("ffrecon")


@dataclass(frozen=True, kw_only=True)
class RunOptions:
    capture: CaptureOptions = field(default_factory=CaptureOptions)
    feedforward: FeedForwardOptions = field(default_factory=FeedForwardOptions)
    overwrite: bool = False
    ground_truth: Path | None = None  # a synthetic scene folder (ground_truth.json) to score against
    command: str = ""  # the command line, recorded in the report


@dataclass(frozen=True)
class RunResult:
    out_dir: Path
    report: dict
    exit_code: int = 0


def run(source: Path, out_dir: Path, model: Path, options: RunOptions = RunOptions()) -> RunResult:
    """Reconstruct ``source`` (folder of photos or a video) with ``model`` into ``out_dir``."""
    report = ReportBuilder()
    report.data.update({"ffrecon_version": __version__, "created": dt.datetime.now().isoformat(timespec="seconds"), "command": options.command, "skipped_stages": [], "timings": {}})
    with staged_output(Path(out_dir), overwrite=options.overwrite) as work:
        t0 = time.perf_counter()
        capture = run_capture(Path(source), options.capture, work)
        report.data["timings"]["capture"] = time.perf_counter() - t0
        add_capture(report, capture)

        ff = run_feedforward(capture, Path(model), options.feedforward, work)
        report.data["timings"]["feedforward"] = ff.seconds
        add_feedforward(report, ff, capture)

        if len(capture.frames) < 2:
            for stage in ("colmap cross-check", "pose comparison", "refinement"):
                report.data["skipped_stages"].append({"stage": stage, "reason": "needs two or more views; this run has one photo (its depth, camera and point cloud are still produced)"})

        write_point_cloud(work / "points.ply", ff.points_xyz, ff.points_rgb)
        write_transforms(work / "transforms.json", [f"images/{n}" for n in capture.names], ff.prediction.cam_from_world, ff.prediction.cameras, ply_file_path="points.ply")
        report.data["outputs"] = {
            "feed-forward COLMAP model": "feedforward/sparse",
            "feed-forward depth maps": "feedforward/depth",
            "nerfstudio transforms": "transforms.json",
            "point cloud": "points.ply",
            "images": "images",
        }
        finish_report(report, ok_message=f"{len(capture.frames)} frame(s) reconstructed")
        report.write(work)
    return RunResult(Path(out_dir), report.data)
