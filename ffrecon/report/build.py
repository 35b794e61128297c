"""report.json (machines) and report.html (people), both built from a run's typed results.

``build_report(results)`` is a pure function of :class:`~ffrecon.results.RunResults` and returns
data only (numbers, names, paths relative to the run folder); each stage of the run's stage list gives its
own entries (:mod:`ffrecon.report.sections`). ``render_html(report, run_dir)``
turns that data into one self-contained page: it computes the table rows and draws the figures,
reading the pictures it shows (frames, depth maps, renders) from the run folder, so a report can be
rebuilt from ``report.json`` and the folder alone. The command-line summary uses
:func:`ffrecon.report.html.summary_rows`, as the page does.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ffrecon import __version__
from ffrecon.colmap_io import is_model_dir
from ffrecon.report.html import render_html
from ffrecon.results import QUICK_STATEMENT, RunMode, RunResults, Skipped
from ffrecon.sfm.refine.options import RefineResult, RefineStatus
from ffrecon.state import each_stage
from ffrecon.timing import Clock


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        return None if not math.isfinite(float(obj)) else float(obj)
    if isinstance(obj, (np.integer, np.bool_)):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    return obj


def _verdict(results: RunResults) -> dict:
    gates = results.gate_results
    failed = [v for g in gates for v in g.failed]
    if any(g.blocking for g in gates):
        message = "; ".join(f"{g.name}: {g.reason} — {g.fix}" for g in failed)
        return {"status": results.verdict.value, "message": message}
    message = f"{len(results.capture.frames)} frame(s) reconstructed"
    return {"status": results.verdict.value, "message": message + (" (failed gates forced past)" if failed else "")}


def _cross_check_note(results: RunResults) -> str | None:
    """The sentence saying that nothing independent checked the model's cameras (None when COLMAP did, or
    made the cameras itself)."""
    if isinstance(results.feedforward, Skipped) or not isinstance(results.colmap, Skipped):
        return None
    quick = results.mode is RunMode.QUICK
    refined = isinstance(results.refine, RefineResult) and results.refine.status is not RefineStatus.FAILED
    if quick and refined:
        return QUICK_STATEMENT
    cameras = "the feed-forward ones refined by bundle adjustment" if refined else "the feed-forward ones, not refined"
    ran = "Quick mode: no" if quick else "No"
    why = "" if quick else f" ({results.colmap.reason})"
    return (
        f"{ran} independent COLMAP cross-check was run{why}; the cameras are {cameras} and are not verified "
        "against an independent reconstruction."
    )


def _timings(results: RunResults) -> dict:
    """Seconds per stage; stages that ran at the same time name each other (``concurrent_with``)."""
    return {
        t.stage: {
            "seconds": t.seconds,
            "reused": t.reused,
            "first_seconds": t.first_seconds,
            "concurrent_with": t.beside,
            "peak_rss_gb": t.peak_rss_gb,
        }
        for t in results.timings
    }


def _concurrent(results: RunResults) -> list[dict]:
    """Groups of stages that ran at the same time: their wall-clock seconds against the sum of theirs."""
    return [
        {"stages": list(o.stages), "wall_seconds": o.wall_seconds, "sum_seconds": o.sum_seconds}
        for o in results.overlaps
    ]


def _final_model(results: RunResults) -> Path | None:
    """sparse/0: every final camera (docs/contracts.md, "Output folder")."""
    folder = results.out_dir / "sparse" / "0"
    return folder if is_model_dir(folder) else None


def _outputs(results: RunResults) -> dict[str, str]:
    """Files for people, relative to the run folder (only those the run wrote)."""
    out = results.out_dir
    ex = results.exports
    ff_sparse = getattr(results.feedforward, "sparse_dir", None)
    candidates = {
        f"final cameras, {getattr(ex, 'cameras_from', '')} (use this)": _final_model(results),
        "refinement's model (refined frames and points)": getattr(results.refine, "model_path", None),
        "COLMAP cross-check model": getattr(results.colmap, "model_path", None),
        "feed-forward COLMAP model": ff_sparse,
        "feed-forward depth maps": None if ff_sparse is None else ff_sparse.parent / "depth",
        "nerfstudio transforms": getattr(ex, "transforms_json", None),
        "point cloud": getattr(ex, "points_ply", None),
        "Gaussian splat": getattr(results.splat, "ply_path", None),
        "fly-through video": getattr(results.splat, "video_path", None),
        "mesh": getattr(ex, "mesh_glb", None),
        "held-out renders": getattr(results.splat, "renders_dir", None),
        "images": results.capture.image_dir,
    }
    return {k: str(Path(v).relative_to(out)) for k, v in candidates.items() if v is not None}


def build_report(results: RunResults) -> dict:
    """The run's machine-readable record (JSON-serialisable; numbers, names, relative paths): the run's header,
    then each stage's entries in run order (:meth:`ffrecon.state.Stage.entries`), then the skips, timings and
    files."""
    report = {
        "ffrecon_version": __version__,
        "created": results.created,
        "command": results.command,
        "forced": results.forced,
        "mode": results.mode.value,
        "cross_check_note": _cross_check_note(results),
        "verdict": _verdict(results),
    }
    for stage in each_stage(results.stages):
        report |= stage.entries(results)
    report |= {
        "skipped_stages": [{"stage": s.stage, "reason": s.reason} for s in results.skipped],
        "timings": _timings(results),
        "concurrent_stages": _concurrent(results),
        "outputs": _outputs(results),
    }
    return _jsonable(report)


def run_timing(seconds: float, cpu_seconds: float, since: str) -> dict:
    """A timings entry of the run's own work (not a stage's): "startup" and "report" (:func:`write_report`)."""
    return {
        "seconds": round(seconds, 4),
        "cpu_seconds": round(cpu_seconds, 4),
        "reused": False,
        "first_seconds": None,
        "concurrent_with": None,
        "peak_rss_gb": None,
        "since": since,
    }


def write_report(
    results: RunResults,
    run_dir: Path,
    *,
    startup: tuple[float, float, str] | None = None,
    report_started: Clock | None = None,
) -> tuple[Path, Path]:
    """Write ``report.html``, then ``report.json`` into ``run_dir`` (the folder ``results`` describe).

    ``startup``: the run's ``(wall, CPU)`` seconds before its first stage and since when (the process's start,
    or the call): the first entry of the timings ("startup"). ``report_started``: when the last stage ended;
    the timings' last entry ("report") is the time from then to the moment before report.json is written:
    the results gathered, this page built and written. report.json cannot hold the time it takes to write
    itself (milliseconds: it is written last), nor what follows (the staging folder swapped into OUT, the
    summary printed, the exit); the page shows "startup" and the stages, report.json "report" too.
    """
    report = build_report(results)
    if startup is not None:
        report["timings"] = {"startup": run_timing(*startup), **report["timings"]}
    html_path = Path(run_dir) / "report.html"
    html_path.write_text(render_html(report, run_dir, results.stages))
    if report_started is not None:
        report["timings"]["report"] = run_timing(*report_started.since(), report_started.origin)
    json_path = Path(run_dir) / "report.json"
    json_path.write_text(json.dumps(report, indent=2))
    return json_path, html_path
