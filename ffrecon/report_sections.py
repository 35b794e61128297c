"""What each stage adds to the report: rows for tables, figures and thumbnails."""

from __future__ import annotations

from ffrecon.capture import Capture
from ffrecon.export.report import ReportBuilder, depth_preview
from ffrecon.models.stage import FeedForwardResult

MAX_THUMBNAILS = 12


def add_capture(report: ReportBuilder, capture: Capture) -> None:
    report.data["inputs"] = capture.to_report()
    report.data["capture_flags"] = [{"frame": f.name, "issue": f.kind, "value": f.value, "what to do": f.message} for f in capture.quality.flags]
    step = max(1, len(capture.frames) // MAX_THUMBNAILS)
    for frame in capture.frames[::step][:MAX_THUMBNAILS]:
        report.add_image("capture", frame.name, frame.image, 160)


def add_feedforward(report: ReportBuilder, ff: FeedForwardResult, capture: Capture) -> None:
    report.data["feedforward"] = ff.to_report()
    pred = ff.prediction
    step = max(1, len(pred) // MAX_THUMBNAILS)
    for k in range(0, len(pred), step)[:MAX_THUMBNAILS]:
        report.add_image("feedforward", f"{pred.names[k]} depth", depth_preview(pred.depth[k]), 160)


def finish_report(report: ReportBuilder, *, ok_message: str) -> None:
    """Verdict, summary and timing rows from what the stages recorded."""
    data = report.data
    failed = [g for g in data.get("gates", []) if g.get("status") == "FAIL"]
    if failed and not data.get("forced"):
        data["verdict"] = {"status": "gate_failed", "message": "; ".join(g["reason"] for g in failed)}
    else:
        data["verdict"] = {"status": "ok", "message": ok_message}
    ff = data.get("feedforward", {})
    data["summary_rows"] = [
        {"item": "frames", "value": data.get("inputs", {}).get("num_frames")},
        {"item": "model", "value": f"{ff.get('model', {}).get('path')} ({ff.get('model', {}).get('family')}{', simulated' if ff.get('model', {}).get('simulated') else ''})"},
        {"item": "fused points", "value": ff.get("num_points")},
        *data.get("extra_summary_rows", []),
    ]
    data["timing_rows"] = [{"stage": k, "seconds": v} for k, v in data.get("timings", {}).items()]
