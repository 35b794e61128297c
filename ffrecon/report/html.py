"""report.html: one self-contained page (figures embedded as base64 PNG) from report.json's data.

The rows of every table and every figure are computed here from the report dict; pictures are read
from the run folder the report describes (``images/``, ``feedforward/depth/``, ``renders/``).
"""

from __future__ import annotations

import html
from pathlib import Path

from ffrecon.report.markup import CSS, MAX_THUMBNAILS, SIMULATED, depth_preview, figure, fmt, table
from ffrecon.report.plots import timings_png
from ffrecon.report.scene3d import scene_html
from ffrecon.report.splat_html import curve_caption, splat_rows, splat_section
from ffrecon.report.stage_html import _calls  # noqa: F401 (tests call it by this name)
from ffrecon.stages import STAGES
from ffrecon.state import Beside, Stage, each_stage

__all__ = ["MAX_THUMBNAILS", "curve_caption", "depth_preview", "render_html", "summary_rows", "wall_seconds"]
_splat = splat_section  # tests call the sections by their old names


def _given_inputs(given: dict) -> str:
    """`` · given: ...`` naming what the user gave besides the photos (escaped), or nothing."""
    parts = []
    if given.get("intrinsics"):
        parts.append(f"intrinsics {given['intrinsics']} ({'fixed' if given.get('intrinsics_fixed') else 'priors'})")
    if given.get("poses"):
        parts.append(f"{given.get('num_poses')} poses from {given['poses']}")
    if given.get("masks"):
        parts.append("masks (masks/)")
    return f" · given: {html.escape('; '.join(parts))}" if parts else ""


def _timings(report: dict, run_dir: Path) -> tuple[list[dict], str]:
    timings = report["timings"]
    if not timings:
        return [], ""
    rows = []
    for stage, t in timings.items():
        status = "reused" if t["reused"] else "ran"
        row = {"stage": stage, "seconds": t["seconds"], "status": status, "when it ran (s)": t["first_seconds"]}
        peak = t.get("peak_rss_gb")
        row |= {"peak memory (GB)": None if peak is None else round(peak, 2)}
        rows.append(row | {"at the same time as": t.get("concurrent_with")})
        if not t["reused"]:
            rows += _step_rows(stage, report.get(stage))
    together = []
    for group in report.get("concurrent_stages", []):
        names = " + ".join(group["stages"])
        rows.append({"stage": f"{names} (wall clock)", "seconds": group["wall_seconds"], "status": "side by side"})
        together.append(
            f"{names} ran at the same time: {group['wall_seconds']:.1f} s wall clock for "
            f"{group['sum_seconds']:.1f} s of stage time"
        )
    rows.append({"stage": "total (wall clock)", "seconds": wall_seconds(report)})
    reused = {s for s, t in timings.items() if t["reused"]}
    shown = {s: (t["first_seconds"] or 0.0) if t["reused"] else t["seconds"] for s, t in timings.items()}
    caption = "Wall-clock seconds per stage on this machine, and per step of the stages that time theirs (with their "
    caption += (
        "CPU seconds: user + system, of the whole process); grey bars: reused from an earlier run (its time then)."
    )
    caption += "".join(f" {text}." for text in together)
    return rows, figure("Time per stage", timings_png(shown, reused), caption)


def _step_rows(stage: str, section) -> list[dict]:
    """One row per step of a stage that times its steps (``timings_s``, and ``cpu_s`` where recorded: user +
    system CPU seconds, the whole process's), under the stage's row."""
    own = section.get("timings_s") if isinstance(section, dict) else None
    if not isinstance(own, dict):
        return []
    cpu = section.get("cpu_s") or {}
    skipped = section.get("skipped_steps") or {}
    rows = [
        {"stage": f"{stage}: {step}", "seconds": seconds, "status": "step", "CPU (s)": cpu.get(step)}
        for step, seconds in own.items()
        if step != "total"
    ]
    rows += [{"stage": f"{stage}: {step}", "status": f"left out: {why}"} for step, why in skipped.items()]
    return rows


def wall_seconds(report: dict) -> float:
    """The stages' wall-clock seconds: their sum, less the overlap of stages that ran at the same time."""
    total = sum(t["seconds"] for t in report["timings"].values())
    return total - sum(g["sum_seconds"] - g["wall_seconds"] for g in report.get("concurrent_stages", []))


def _sections(stages: tuple[Stage | Beside, ...]) -> list:
    """The page's sections in order: each stage's (:attr:`ffrecon.state.Stage.page`), in run order, then the
    timings."""
    return [section for stage in each_stage(stages) for section in stage.page] + [("Timings", _timings)]


def _frame_verdicts(evidence: dict) -> str:
    """``confirmed: 6, contradicted: 1 (frame_005.png), unchecked: 1 (frame_007.png)``: the others are named."""
    parts = []
    for verdict, names in evidence.get("verdicts", {}).items():
        if names:
            listed = ", ".join(names[:4]) + (", ..." if len(names) > 4 else "")
            shown = "" if verdict == "confirmed" else f" ({listed})"
            parts.append(f"{verdict}: {len(names)}{shown}")
    return ", ".join(parts)


def summary_rows(report: dict) -> list[tuple[str, str]]:
    """``(item, value)`` lines of the run's summary, for the page and the terminal."""
    ff = report["feedforward"]
    rows = [("frames", str(report["inputs"]["num_frames"]))]
    if report.get("mode") == "quick":
        rows.append(("mode", "quick (--quick): no COLMAP reconstruction"))
    if report.get("cross_check_note"):
        rows.append(("cross-check", report["cross_check_note"]))
    if "skipped" in ff:
        rows.append(("model", "none: cameras from COLMAP"))
    else:
        model = ff["model"]
        rows.append(
            ("model", f"{Path(model['path']).name} ({model['family']}{', SIMULATED' if model['simulated'] else ''})")
        )
        rows.append(("fused points", str(ff["num_points"])))
    exports = report["exports"]
    if "skipped" not in exports:
        missing = exports.get("not_written", {}).get("points.ply")
        cloud = f"not written: {missing}" if missing else f"{exports['num_points']} {exports['points']}"
        rows.append(("exported cameras", f"{exports['cameras']}; points.ply: {cloud}"))
    colmap, refine, splat = report["colmap"], report["refine"], report["splat"]
    if "skipped" not in colmap:
        runs = "; ".join(f"{r['mapper']}: {r['num_registered']}" for r in colmap.get("mapper_runs", []))
        mapper = (
            f" ({colmap['mapper']} mapper; {runs})" if colmap.get("mapper") and len(colmap["mapper_runs"]) > 1 else ""
        )
        if colmap.get("mapper") == "two_view":
            mapper = (
                " (two-view reconstruction built by ffrecon from COLMAP's verified matches; its mappers built none)"
            )
        err = colmap.get("mean_reprojection_error_px")
        err_text = f", {err:.2f} px" if err is not None else ""
        rows.append(("COLMAP registered", f"{colmap['num_registered']}/{colmap['num_images']}{mapper}{err_text}"))
    if "skipped" not in refine:
        err = refine.get("mean_reprojection_error_px")
        err_text = f"{err:.2f}" if err is not None else "nan"
        rows.append(("refined frames", f"{refine['num_refined']}/{refine['num_images']} (reprojection {err_text} px)"))
    for comp in report["pose_errors"].values():
        m = comp["metrics"]
        rot = m["median_rotation_deg"] if m["median_rotation_deg"] is not None else float("nan")
        ate = m["ATE_relative"] if m["ATE_relative"] is not None else float("nan")
        value = f"AUC@5 {m['AUC@5']:.3f}, median rotation {rot:.3f} deg, ATE {ate:.2%} of extent"
        rows.append((f"{comp['estimate']} vs {comp['reference']}", value))
    if "skipped" not in splat:
        rows += splat_rows(splat)
    evidence = report["evidence"]
    if "skipped" not in evidence:
        rows.append(("final cameras", _frame_verdicts(evidence)))
    reused = [stage for stage, t in report["timings"].items() if t["reused"]]
    if reused:
        rows.append(("reused from an earlier run", ", ".join(reused)))
    return rows


def render_html(report: dict, run_dir: Path, stages: tuple[Stage | Beside, ...] = STAGES) -> str:
    """The whole page: verdict banner, summary, then one section per stage with figures and tables.

    Args:
        report: what :func:`ffrecon.report.build.build_report` returns (or report.json, read back).
        run_dir: the run folder the report describes; the frames, depth maps and renders shown are read
            from it (missing ones are left out).
        stages: the stage list that made the report; each stage gives its sections.
    """
    run_dir = Path(run_dir)
    inputs = report["inputs"]
    created = f"{fmt(report.get('created'))} · ffrecon {fmt(report.get('ffrecon_version'))}"
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'><title>ffrecon report</title>"
        f"<style>{CSS}</style></head><body>",
        f"<h1>ffrecon report</h1><p class='muted'>{created} · input {fmt(inputs.get('source'))}"
        f"{_given_inputs(inputs.get('given') or {})}</p>",
    ]
    verdict = report["verdict"]
    banner = "ok" if verdict["status"] == "ok" else "bad"
    status = html.escape(verdict["status"].upper())
    parts.append(f"<div class='banner {banner}'><b>{status}</b> — {html.escape(verdict['message'])}</div>")
    if report.get("cross_check_note"):
        parts.append(
            f"<div class='banner warn'><b>Not cross-checked.</b> {html.escape(report['cross_check_note'])}</div>"
        )
    if report["feedforward"].get("model", {}).get("simulated"):
        parts.append(SIMULATED)
    for item in report["skipped_stages"]:
        stage, reason = html.escape(item["stage"]), html.escape(item["reason"])
        parts.append(f"<div class='banner warn'>Skipped <b>{stage}</b>: {reason}</div>")
    for file, reason in (report["exports"].get("not_written") or {}).items():
        parts.append(f"<div class='banner warn'>Not written <b>{html.escape(file)}</b>: {html.escape(reason)}</div>")
    parts.append("<h2>Summary</h2>" + table([{"item": k, "value": v} for k, v in summary_rows(report)]))
    scene = scene_html(report, run_dir)
    if scene:
        caption = (
            "Drag to turn, scroll to zoom, hover for names. The final cameras as frustums (red: frames the checks "
            "flagged), the other estimates' camera centres moved onto them by a Sim(3), and a sample of points.ply. "
            "ffrecon view OUT shows the same with the splat and the photos."
        )
        parts.append(f"<h2>The scene in 3D</h2>{scene}<p class='muted'>{html.escape(caption)}</p>")
    for title, section in _sections(stages):
        rows, body = section(report, run_dir)
        if rows or body:
            parts.append(f"<h2>{html.escape(title)}</h2>" + table(rows) + body)
    files = [{"file": k, "path": v} for k, v in report["outputs"].items()]
    parts.append("<h2>Files</h2>" + table(files))
    parts.append("<p class='muted'>Full machine-readable record: report.json</p></body></html>")
    return "".join(parts)
