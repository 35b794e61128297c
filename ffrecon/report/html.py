"""report.html: one self-contained page (figures embedded as base64 PNG) from report.json's data.

The rows of every table and every figure are computed here from the report dict; pictures are read
from the run folder the report describes (``images/``, ``feedforward/depth/``, ``renders/``).
"""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from ffrecon.report.markup import (
    CSS,
    MAX_THUMBNAILS,
    SIMULATED,
    depth_preview,
    every,
    figure,
    fmt,
    gallery,
    table,
    thumb,
)
from ffrecon.report.plots import PathSeries, camera_paths_png, error_bars_png, thumbnail_png, timings_png
from ffrecon.report.scene3d import scene_html
from ffrecon.report.splat_html import curve_caption, seeds_section, splat_rows, splat_section
from ffrecon.sfm import DisagreementOptions

__all__ = ["MAX_THUMBNAILS", "curve_caption", "depth_preview", "render_html", "summary_rows", "wall_seconds"]
_splat = splat_section  # tests call the sections by their old names


_DISAGREEMENT = DisagreementOptions()  # the plot's threshold lines: the evidence's defaults


def _capture(report: dict, run_dir: Path) -> tuple[list[dict], str]:
    """The quality flags as a table, and thumbnails of an even sample of the frames plus every flagged
    frame (up to the sample's size again), the flagged ones framed in red with what was found."""
    flags = report["inputs"]["quality"]["flags"]
    rows = [{"frame": f["name"], "issue": f["kind"], "value": f["value"], "what to do": f["message"]} for f in flags]
    names = report["inputs"]["names"]
    issues: dict[str, list[str]] = {}
    for f in flags:
        issues.setdefault(f["name"], []).append(str(f["kind"]))
    shown = set(every(names)) | set(list(issues)[:MAX_THUMBNAILS])
    captions = {n: f"{n}: {', '.join(issues[n])}" if n in issues else n for n in names}
    thumbs = [t for n in names if n in shown for t in thumb(run_dir / "images" / n, captions[n], 160)]
    note = ""
    if issues:
        note = f"<p class='muted'>Framed in red: the {len(issues)} frame(s) the capture checks flagged.</p>"
    return rows, note + gallery(thumbs, flagged=frozenset(captions[n] for n in issues))


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


def _given_intrinsics(given: dict | None) -> str:
    """One line: the given focal length beside the model's own estimate and the final one."""
    if not given:
        return ""

    def focal(part: dict) -> str:
        f, d = part["focal_px"], part["vs_given"]
        return "not measured" if f is None else f"{f:.2f} px ({100 * d:+.2f}%)"

    how = "fixed" if given["fixed"] else "as starting values"
    return (
        f"given ({given['file']}, {how}): focal {given['given_focal_px']:.2f} px; the model's own estimate "
        f"{focal(given['model'])}; final {focal(given['final'])}"
    )


def _calls(chunks: dict | None) -> str | None:
    """The chunk layout and the loop pass in a sentence (``feedforward.chunks``); None for one call."""
    if not chunks or len(chunks["calls"]) < 2:
        return None
    text = f"{len(chunks['calls'])} chunks of {chunks['size']} frames sharing {chunks['overlap']} ({chunks['engine']})"
    loops = chunks.get("loops")
    if loops is None:
        return text + "; no loop pass"
    used = [c for c in loops["calls"] if c["used"]]
    if not used:
        return text + f"; loop calls: none used of {len(loops['calls'])} ({loops['candidates']} revisits found)"
    missed = max(c["closure_deg"] for c in used)
    return text + (
        f"; {len(used)} loop calls closed the chain (it missed by up to {missed:.2f} deg; "
        f"chunks moved by up to {loops['max_correction_deg']:.2f} deg)"
    )


def _feedforward(report: dict, run_dir: Path) -> tuple[list[dict], str]:
    ff = report["feedforward"]
    if "skipped" in ff:
        return [], ""
    model = ff["model"]
    items = [
        ("intrinsics", _given_intrinsics(report.get("intrinsics"))),
        ("world frame", ff.get("world_frame")),
        ("assumptions", ff.get("assumptions")),
        ("model notes", model.get("notes")),
        ("model", model.get("description")),
        ("model calls", _calls(ff.get("chunks"))),
    ]
    previews = []
    for name in every(report["inputs"]["names"]):
        path = run_dir / "feedforward" / "depth" / f"{Path(name).stem}.npz"
        if path.is_file():
            with np.load(path) as data:
                previews.append((f"{name} depth", thumbnail_png(depth_preview(data["depth"]), max_side=160)))
    return [{"item": k, "value": v} for k, v in items if v], gallery(previews)


def _error_row(comp: dict) -> dict:
    m = comp["metrics"]
    rates = {k: v for k, v in m.items() if k.startswith(("RRA@", "RTA@", "AUC@"))}
    return {
        "comparison": f"{comp['estimate']} vs {comp['reference']}",
        "registered": f"{m['num_registered']}/{m['num_images']}",
        **rates,
        "ATE": m["ATE"],
        "ATE/extent": m["ATE_relative"],
        "median rot (deg)": m["median_rotation_deg"],
        "disagreeing": len(comp["disagreeing"]),
    }


def _nan_array(values) -> np.ndarray:
    return np.array([[np.nan] * 3 if v is None else v for v in values], float)


def _poses(report: dict, run_dir: Path) -> tuple[list[dict], str]:
    rows = [_error_row(c) for c in report["pose_errors"].values()]
    plot = report.get("pose_plot")
    if not plot:
        return rows, ""
    names, ref = plot["names"], plot["reference"]
    ref_centers = _nan_array(plot["reference_centers"])
    series = [PathSeries(ref, ref_centers)] + [PathSeries(k, _nan_array(v)) for k, v in plot["aligned_centers"].items()]
    highlight = [names.index(n) for n in plot["disagreeing"]]
    paths = camera_paths_png(series, up=np.array(plot["up"]), names=names, highlight=highlight)
    finite = ref_centers[np.all(np.isfinite(ref_centers), axis=1)]
    extent = float(np.linalg.norm(finite.max(0) - finite.min(0))) if len(finite) else 1.0
    as_array = lambda v: np.array([np.nan if x is None else x for x in v], float)  # noqa: E731
    bars = error_bars_png(
        names,
        {k: as_array(v) for k, v in plot["rotation_deg"].items()},
        {k: as_array(v) / max(extent, 1e-12) for k, v in plot["center_error"].items()},
        rotation_threshold_deg=_DISAGREEMENT.max_rotation_deg,
        center_threshold=_DISAGREEMENT.max_center_error,
        center_unit=f"fraction of the {ref} camera extent",
    )
    parts = [
        figure(
            f"Camera paths aligned to {ref}",
            paths,
            f"Top-down view of the camera centres, each set Sim(3)-aligned to {ref}; "
            "red circles mark images that disagree.",
        ),
        figure(
            "Per-image error",
            bars,
            f"Rotation and centre error of each image against {ref}: rotations after their best common "
            "rotation, centres after a Sim(3) fit of the centres.",
        ),
    ]
    thumbs = []
    for comp in report["pose_errors"].values():
        for d in comp["disagreeing"][:MAX_THUMBNAILS]:
            caption = f"{d['name']}: {comp['estimate']} vs {comp['reference']}: {d['reason']}"
            thumbs += thumb(run_dir / "images" / d["name"], caption, 200)
    return rows, "".join(parts) + gallery(thumbs)


def _refine(report: dict, run_dir: Path) -> tuple[list[dict], str]:
    data = report["refine"]
    if "skipped" in data:
        return [], ""
    return [{"frame": w["name"], "status": "FLAGGED", "why": w["message"]} for w in data["flagged"]], ""


def _gate_rows(verdicts: list[dict], witness_note: str) -> list[dict]:
    keys = ("name", "status", "value", "threshold", "reason", "fix")
    rows = []
    for v in verdicts:
        row = {k: v[k] for k in keys}
        row["causes"] = v["causes"]
        row["stops the run"] = "yes" if v["blocking"] else witness_note
        rows.append(row)
    return rows


def _gates(report: dict, run_dir: Path) -> tuple[list[dict], str]:
    gates = report["gates"]
    if isinstance(gates, dict):
        return [], ""
    return _gate_rows(gates, "no: COLMAP is a witness; the final cameras are judged below"), ""


def _evidence(report: dict, run_dir: Path) -> tuple[list[dict], str]:
    data = report["evidence"]
    if "skipped" in data:
        return [], ""
    rows = _gate_rows(data["gates"], "no: the run goes on from COLMAP's cameras")
    per_image = [
        {"frame": e["name"], "verdict": e.get("verdict", ""), "evidence": e["status"], "why": e["why"]}
        for e in data["per_image"]
    ]
    counts = ", ".join(f"{k}: {len(v)}" for k, v in data.get("verdicts", {}).items() if v) or ", ".join(
        f"{k}: {v}" for k, v in data["counts"].items() if v
    )
    body = f"<p>Per image ({html.escape(counts)}):</p>" + table(per_image)
    if data["model_unsuited"]:
        body = f"<div class='banner warn'>{html.escape(data['unsuited_reason'])}</div>" + body
    return rows, body


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


_SECTIONS = (
    ("Capture", _capture),
    ("Feed-forward cameras and depth", _feedforward),
    ("Verification gates", _gates),
    ("Pose error", _poses),
    ("Refinement", _refine),
    ("Final cameras: the evidence", _evidence),
    ("Gaussian splat", splat_section),
    ("Seeds compared: feed-forward depth vs SfM points", seeds_section),
    ("Timings", _timings),
)


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


def render_html(report: dict, run_dir: Path) -> str:
    """The whole page: verdict banner, summary, then one section per stage with figures and tables.

    Args:
        report: what :func:`ffrecon.report.build.build_report` returns (or report.json, read back).
        run_dir: the run folder the report describes; the frames, depth maps and renders shown are read
            from it (missing ones are left out).
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
    for title, section in _SECTIONS:
        rows, body = section(report, run_dir)
        if rows or body:
            parts.append(f"<h2>{html.escape(title)}</h2>" + table(rows) + body)
    files = [{"file": k, "path": v} for k, v in report["outputs"].items()]
    parts.append("<h2>Files</h2>" + table(files))
    parts.append("<p class='muted'>Full machine-readable record: report.json</p></body></html>")
    return "".join(parts)
