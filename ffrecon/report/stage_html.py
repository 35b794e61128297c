"""report.html's sections of the capture, feed-forward, gates, refinement, evidence and pose-comparison stages:
each takes report.json's dict and the run folder and returns ``(table rows, html)``, as
:attr:`ffrecon.state.Stage.page` asks (the stage list, :mod:`ffrecon.stages`, names each stage's)."""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from ffrecon.report.markup import MAX_THUMBNAILS, depth_preview, every, figure, gallery, table, thumb
from ffrecon.report.plots import PathSeries, camera_paths_png, error_bars_png, thumbnail_png
from ffrecon.sfm.compare.poses import DisagreementOptions

_DISAGREEMENT = DisagreementOptions()  # the plot's threshold lines: the evidence's defaults


def capture_section(report: dict, run_dir: Path) -> tuple[list[dict], str]:
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


def feedforward_section(report: dict, run_dir: Path) -> tuple[list[dict], str]:
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


def poses_section(report: dict, run_dir: Path) -> tuple[list[dict], str]:
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


def refine_section(report: dict, run_dir: Path) -> tuple[list[dict], str]:
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


def gates_section(report: dict, run_dir: Path) -> tuple[list[dict], str]:
    gates = report["gates"]
    if isinstance(gates, dict):
        return [], ""
    return _gate_rows(gates, "no: COLMAP is a witness; the final cameras are judged below"), ""


def evidence_section(report: dict, run_dir: Path) -> tuple[list[dict], str]:
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
    if data.get("refinement_set_aside"):
        body = f"<div class='banner warn'>{html.escape(data['refinement_set_aside'])}</div>" + body
    return rows, body
