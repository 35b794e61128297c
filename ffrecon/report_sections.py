"""What each stage adds to the report: rows for tables, figures and thumbnails."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ffrecon.capture import Capture
from ffrecon.export.report import Figure, ReportBuilder, depth_preview, timings_png
from ffrecon.models.stage import FeedForwardResult

log = logging.getLogger("ffrecon")
MAX_THUMBNAILS = 12


def add_capture(report: ReportBuilder, capture: Capture) -> None:
    report.data["inputs"] = capture.to_report()
    report.data["capture_flags"] = [
        {"frame": f.name, "issue": f.kind, "value": f.value, "what to do": f.message} for f in capture.quality.flags
    ]
    step = max(1, len(capture.frames) // MAX_THUMBNAILS)
    for frame in capture.frames[::step][:MAX_THUMBNAILS]:
        report.add_image("capture", frame.name, frame.image, 160)


def add_feedforward(report: ReportBuilder, ff: FeedForwardResult) -> None:
    report.data["feedforward"] = ff.to_report()
    pred = ff.prediction
    step = max(1, len(pred) // MAX_THUMBNAILS)
    for k in range(0, len(pred), step)[:MAX_THUMBNAILS]:
        report.add_image("feedforward", f"{pred.names[k]} depth", depth_preview(pred.depth[k]), 160)


def load_references(
    ground_truth: Path | None, reference: Path | None, names
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Reference poses by label: ``{"ground truth": (cam_from_world [N,3,4], registered [N])}``."""
    refs = {}
    if ground_truth is not None:
        from ffrecon.synthetic import load_scene

        scene = load_scene(Path(ground_truth))
        index = {n: k for k, n in enumerate(scene.names)}
        have = np.array([n in index for n in names])
        poses = np.stack([scene.cam_from_world[index[n]] if n in index else np.eye(3, 4) for n in names])
        refs["ground truth"] = (poses, have)
    if reference is not None:
        import pycolmap

        from ffrecon.sfm.colmap_io import cam_from_world_by_name

        refs["reference model"] = cam_from_world_by_name(pycolmap.Reconstruction(str(reference)), names)
    return refs


def add_colmap(report: ReportBuilder, colmap) -> None:
    report.data["colmap"] = colmap.to_report()


def add_gates(report: ReportBuilder, capture: Capture, ff: FeedForwardResult, colmap, options) -> list:
    from ffrecon.sfm.gates import GateOptions, evaluate_gates

    verdicts = evaluate_gates(
        colmap=colmap, prediction=ff.prediction, image_dir=capture.image_dir, options=options or GateOptions()
    )
    report.data["gates"] = [v.to_report() for v in verdicts]
    return verdicts


def add_refine(report: ReportBuilder, refined) -> None:
    report.data["refine"] = refined.to_report()
    report.data["refine_rows"] = [
        {"frame": w["name"], "status": "FLAGGED", "why": w["message"]} for w in report.data["refine"]["flagged"]
    ]


def _error_row(comp) -> dict:
    err = comp.errors
    return {
        "comparison": f"{comp.estimate} vs {comp.reference}",
        "registered": f"{err.num_registered}/{err.num_images}",
        **{f"RRA@{k}": err.rra[k] for k in err.rra},
        **{f"RTA@{k}": err.rta[k] for k in err.rta},
        **{f"AUC@{k}": err.auc[k] for k in err.auc},
        "ATE": err.ate,
        "ATE/extent": err.ate_relative,
        "median rot (deg)": err.median_rotation_deg,
        "disagreeing": len(comp.disagreements),
    }


def add_pose_comparisons(
    report: ReportBuilder, capture: Capture, ff: FeedForwardResult, colmap, refined, truth: dict
) -> dict:
    """Pose error: feed-forward vs COLMAP, every estimate vs each reference; plots and thumbnails."""
    from ffrecon.export.plots import PathSeries, camera_paths_png, error_bars_png, up_from_cameras
    from ffrecon.sfm.compare import compare_poses

    names = list(capture.names)
    n = len(names)
    estimates = {"feed-forward": (ff.prediction.cam_from_world, np.ones(n, bool))}
    if colmap is not None and colmap.num_registered >= 2:
        estimates["COLMAP"] = (colmap.cam_from_world, colmap.registered)
    if refined is not None:
        estimates["refined"] = (refined.cam_from_world, refined.registered)
    comparisons = []
    if "COLMAP" in estimates:
        poses, reg = estimates["COLMAP"]
        comparisons.append(
            compare_poses(
                ff.prediction.cam_from_world,
                poses,
                names,
                None,
                ref_registered=reg,
                estimate="feed-forward",
                reference="COLMAP",
            )
        )
    # Plots use the most trustworthy reference: ground truth, a reference model, else COLMAP.
    primary: list = []
    for ref_label, (ref_poses, ref_have) in truth.items():
        group = [
            compare_poses(
                poses, ref_poses, names, reg, ref_registered=ref_have, estimate=est_label, reference=ref_label
            )
            for est_label, (poses, reg) in estimates.items()
        ]
        comparisons += group
        primary = primary or group
    primary = primary or comparisons[:1]
    report.data["pose_errors"] = {
        f"{c.estimate}_vs_{c.reference}".replace(" ", "_").replace("-", "").lower(): c.to_report() for c in comparisons
    }
    report.data["pose_error_rows"] = [_error_row(c) for c in comparisons]
    if not primary or n < 2:
        return report.data["pose_errors"]
    ref = primary[0]
    series = [PathSeries(ref.reference, ref.reference_centers)] + [
        PathSeries(c.estimate, c.aligned_centers) for c in primary
    ]
    ref_poses = truth[ref.reference][0] if ref.reference in truth else estimates["COLMAP"][0]
    disagreeing = sorted({names.index(d) for c in primary for d in c.disagreeing})
    report.add_figure(
        "poses",
        Figure(
            f"Camera paths aligned to {ref.reference}",
            camera_paths_png(series, up=up_from_cameras(ref_poses), names=names, highlight=disagreeing),
            f"Top-down view of the camera centres, each set Sim(3)-aligned to {ref.reference}; red circles mark images that disagree.",
        ),
    )
    extent = float(np.linalg.norm(np.nanmax(ref.reference_centers, 0) - np.nanmin(ref.reference_centers, 0)))
    report.add_figure(
        "poses",
        Figure(
            "Per-image error",
            error_bars_png(
                names,
                {c.estimate: c.per_image_rotation_deg for c in primary},
                {c.estimate: c.per_image_center_error / max(extent, 1e-12) for c in primary},
                rotation_threshold_deg=5.0,
                center_threshold=0.05,
                center_unit=f"fraction of the {ref.reference} camera extent",
            ),
            f"Rotation and centre error of each image against {ref.reference}, after the Sim(3) alignment.",
        ),
    )
    for c in comparisons:
        for d in c.disagreements[:MAX_THUMBNAILS]:
            k = names.index(d.name)
            report.add_image(
                "poses", f"{d.name}: {c.estimate} vs {c.reference}: {d.reason}", capture.frames[k].image, 200
            )
    return report.data["pose_errors"]


def add_splat(report: ReportBuilder, splat) -> None:
    import cv2

    data = splat.to_report()
    report.data["splat"] = data
    mean = data["heldout_mean"]
    report.data["splat_rows"] = [
        {
            "measure": "held-out PSNR (dB)",
            "seed": mean.get("psnr_seed"),
            "optimised": mean.get("psnr_optimized"),
            "after cleaning": mean.get("psnr_cleaned"),
        },
        {
            "measure": "held-out SSIM",
            "seed": mean.get("ssim_seed"),
            "optimised": mean.get("ssim_optimized"),
            "after cleaning": mean.get("ssim_cleaned"),
        },
        {
            "measure": "Gaussians",
            "seed": data["gaussians"]["seed"],
            "optimised": data["gaussians"]["optimized"],
            "after cleaning": data["gaussians"]["cleaned"],
        },
        {
            "measure": "iterations (per second)",
            "seed": None,
            "optimised": f"{data['iterations']} ({data['iterations_per_second']:.2f}/s)",
            "after cleaning": None,
        },
    ]
    for caption, path in splat.report_images():
        rgb = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
        report.add_image("splat", caption, rgb, 240)


def add_outputs(report: ReportBuilder, work: Path) -> None:
    candidates = {
        "refined COLMAP model (use this)": "sparse/0",
        "COLMAP cross-check model": "colmap/sparse/0",
        "feed-forward COLMAP model": "feedforward/sparse",
        "feed-forward depth maps": "feedforward/depth",
        "nerfstudio transforms": "transforms.json",
        "point cloud": "points.ply",
        "Gaussian splat": "splat.ply",
        "fly-through video": "flythrough.mp4",
        "mesh": "mesh.glb",
        "held-out renders": "renders",
        "images": "images",
    }
    report.data["outputs"] = {k: v for k, v in candidates.items() if (work / v).exists()}


def finish_report(report: ReportBuilder, *, ok_message: str) -> None:
    """Verdict, summary and timing rows from what the stages recorded."""
    data = report.data
    failed = [g for g in data.get("gates", []) if g.get("status") == "fail"]
    if failed and not data.get("forced"):
        data["verdict"] = {
            "status": "gate_failed",
            "message": "; ".join(f"{g['name']}: {g['reason']} — {g.get('fix', '')}" for g in failed),
        }
    else:
        data["verdict"] = {"status": "ok", "message": ok_message + (" (failed gates forced past)" if failed else "")}
    ff = data.get("feedforward", {})
    rows = [
        {"item": "frames", "value": data.get("inputs", {}).get("num_frames")},
        {
            "item": "model",
            "value": f"{Path(ff.get('model', {}).get('path', '?')).name} ({ff.get('model', {}).get('family')}{', SIMULATED' if ff.get('model', {}).get('simulated') else ''})",
        },
        {"item": "fused points", "value": ff.get("num_points")},
    ]
    if "colmap" in data:
        rows.append(
            {"item": "COLMAP registered", "value": f"{data['colmap']['num_registered']}/{data['colmap']['num_images']}"}
        )
    if "refine" in data:
        rows.append(
            {
                "item": "refined frames",
                "value": f"{data['refine']['num_refined']}/{data['refine']['num_images']} (reprojection {data['refine'].get('mean_reprojection_error_px') or float('nan'):.2f} px)",
            }
        )
    for comp in data.get("pose_errors", {}).values():
        m = comp["metrics"]
        rows.append(
            {
                "item": f"{comp['estimate']} vs {comp['reference']}",
                "value": f"AUC@5 {m['AUC@5']:.3f}, median rotation {m['median_rotation_deg'] or float('nan'):.3f} deg, ATE {m['ATE_relative'] or float('nan'):.2%} of extent",
            }
        )
    if "splat" in data:
        m = data["splat"]["heldout_mean"]
        if m.get("psnr_seed") is not None and m.get("psnr_cleaned") is not None:
            rows.append(
                {
                    "item": "splat held-out PSNR",
                    "value": f"{m['psnr_seed']:.2f} dB (seed) -> {m['psnr_cleaned']:.2f} dB ({data['splat']['iterations']} iterations, {data['splat']['gaussians']['cleaned']} Gaussians)",
                }
            )
    data["summary_rows"] = rows
    data["timing_rows"] = [{"stage": k, "seconds": v} for k, v in data.get("timings", {}).items()]
    if data.get("timings"):
        report.add_figure(
            "timings",
            Figure("Time per stage", timings_png(data["timings"]), "Wall-clock seconds per stage on this machine."),
        )
