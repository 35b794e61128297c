"""report.html's splat sections: the splat's held-out scores, curve, cleaning, pose refinement and fly-through, and
the two seeds compared."""

from __future__ import annotations

import base64
import html
from pathlib import Path

import numpy as np

from ffrecon.report.markup import field_default, figure, gallery, ordinal, table, thumb
from ffrecon.report.media import animated_webp, video_frames
from ffrecon.report.plots import curves_png
from ffrecon.splat.options import SplatOptions


def curve_caption() -> str:
    """The held-out curve's caption; the held-out frames as :class:`~ffrecon.splat.stage.SplatOptions` picks them."""
    return (
        f"Mean held-out PSNR and SSIM (every {ordinal(field_default(SplatOptions, 'holdout_every'))} frame "
        "by default, never trained on; plain renders before cleaning) against optimisation seconds, from the "
        "seed on."
    )


def splat_section(report: dict, run_dir: Path) -> tuple[list[dict], str]:
    data = report["splat"]
    if "skipped" in data:
        return [], ""
    mean = data["heldout_mean"]
    rows = [
        {"measure": f"held-out {label}", **{col: mean.get(f"{key}_{s}") for col, s in _SPLAT_COLUMNS}}
        for label, key in (("PSNR (dB)", "psnr"), ("SSIM", "ssim"))
    ]
    corrected = {f"{key}_cleaned_color_corrected": key for key in ("psnr", "ssim")}
    rows += [
        {"measure": f"held-out {key.upper()}, colour-corrected", "after cleaning": mean.get(name)}
        for name, key in corrected.items()
        if mean.get(name) is not None
    ]
    counts = data["gaussians"]
    rows.append({"measure": "Gaussians", **{col: counts[s] for col, s in _SPLAT_COLUMNS}})
    rate = f"{data['iterations']} ({data['iterations_per_second']:.2f}/s)"
    rows.append({"measure": "iterations (per second)", "seed": None, "optimised": rate, "after cleaning": None})
    psnr = {v["name"]: v for v in data["heldout_per_view"]}
    curve = ""
    if data.get("heldout_curve"):
        curve = figure(
            "Held-out quality over optimisation time", curves_png({"splat": data["heldout_curve"]}), curve_caption()
        )
    thumbs = []
    for r in data["renders"]:
        m = psnr[r["view"]]
        for caption, key in (
            (f"{r['view']}: ground truth", "truth"),
            (f"{r['view']}: seed, PSNR {m['psnr_seed']:.1f} dB", "seed"),
            (f"{r['view']}: splat, PSNR {m['psnr_cleaned']:.1f} dB", "splat"),
        ):
            thumbs += thumb(run_dir / r[key], caption, 240)
    poses = _pose_refinement_table(data.get("pose_refinement", []), data.get("depth_prior", False))
    cleaning = _cleaning_table(data.get("cleaning", {}).get("steps", []))
    return rows, _flythrough(run_dir / "flythrough.mp4") + curve + cleaning + poses + gallery(thumbs, wide=True)


def _cleaning_table(steps: list[dict]) -> str:
    """Each cleaning step: what it would remove, whether it was kept, and its effect on held-out PSNR."""
    if not steps:
        return ""
    rows = [
        {
            "step": s["step"].replace("_", " "),
            "Gaussians it would remove": s["candidates"],
            "applied": "yes" if s["applied"] else "no",
            "held-out PSNR with it (dB)": s.get("psnr_after"),
            "why": s["reason"],
        }
        for s in steps
    ]
    caption = (
        "Each step was tried on the held-out views and kept only while the splat stayed within 0.1 dB of the "
        "trained one (a crop box you gave is always applied)."
    )
    return f"<h3>Cleaning</h3><p class='muted'>{html.escape(caption)}</p>" + table(rows)


def _pose_refinement_summary(changes: list[dict]) -> str:
    rotation = float(np.median([c["rotation_deg"] for c in changes]))
    flagged = [c["name"] for c in changes if c["flagged"]]
    text = f"{len(changes)} unconfirmed frame(s) refined photometrically, median change {rotation:.2f} deg"
    return text + (f"; still fitting poorly: {', '.join(flagged)}" if flagged else "")


def _pose_refinement_table(changes: list[dict], depth_prior: bool) -> str:
    """Per frame the splat's photometric pose correction (frames no evidence confirmed) and its fit."""
    prior = " The model's depth was a prior in the loss (few views)." if depth_prior else ""
    if not changes:
        return f"<p class='muted'>{prior.strip()}</p>" if prior else ""
    rows = [
        {
            "frame": c["name"],
            "rotation change (deg)": c["rotation_deg"],
            "centre move (% of scene)": 100 * c["translation"],
            "PSNR of its own photo (dB)": c["psnr"],
            "fit": "poor: camera may be wrong" if c["flagged"] else "ok",
        }
        for c in changes
    ]
    caption = (
        "Cameras no independent evidence confirmed were optimised with the Gaussians (bounded); a frame whose "
        "render still misses its photo by several dB more than the others is flagged." + prior
    )
    return f"<h3>Photometric pose refinement</h3><p class='muted'>{html.escape(caption)}</p>" + table(rows)


def _flythrough(path: Path) -> str:
    """flythrough.mp4 as an inline animated WebP ('' when there is no video or it cannot be read)."""
    frames, fps = video_frames(path) if path.is_file() else ([], 0.0)
    if not frames:
        return ""
    data = base64.b64encode(animated_webp(frames, fps)).decode()
    caption = "The splat along a smooth path through the cameras (flythrough.mp4, shrunk, every few frames)."
    return (
        f"<figure><img alt='fly-through of the splat' src='data:image/webp;base64,{data}'>"
        f"<figcaption class='muted'>{html.escape(caption)}</figcaption></figure>"
    )


_SPLAT_COLUMNS = (("seed", "seed"), ("optimised", "optimized"), ("after cleaning", "cleaned"))


def seeds_section(report: dict, run_dir: Path) -> tuple[list[dict], str]:
    other = report.get("seed_comparison")
    if not other or "skipped" in other or "skipped" in report["splat"]:
        return [], ""
    ff = report["splat"]
    rows = []
    for label, data in (("feed-forward depth (no SfM)", ff), ("COLMAP's points (SfM)", other)):
        mean = data["heldout_mean"]
        rows.append(
            {
                "seed": label,
                "seed Gaussians": data["gaussians"]["seed"],
                "held-out PSNR (dB)": mean.get("psnr_cleaned"),
                "held-out SSIM": mean.get("ssim_cleaned"),
                "colour-corrected PSNR": mean.get("psnr_cleaned_color_corrected"),
                "iterations": data["iterations"],
            }
        )
    curves = {"feed-forward seed": ff["heldout_curve"], "SfM seed": other["heldout_curve"]}
    if not all(curves.values()):
        return rows, ""
    caption = "Both splats train on the same views and cameras under the same budget; scored on held-out views."
    return rows, figure("Held-out quality over time", curves_png(curves), caption)


def splat_rows(splat: dict) -> list[tuple[str, str]]:
    """The summary's splat lines: the written splat's held-out PSNR (the trained one beside it), pose changes."""
    rows = []
    m = splat["heldout_mean"]
    if m.get("psnr_seed") is not None and m.get("psnr_cleaned") is not None:
        value = (
            f"{m['psnr_seed']:.2f} dB (seed) -> {m['psnr_cleaned']:.2f} dB written (trained "
            f"{m.get('psnr_optimized') or float('nan'):.2f} dB before cleaning; {splat['iterations']} iterations, "
            f"{splat['gaussians']['cleaned']} Gaussians)"
        )
        rows.append(("splat held-out PSNR", value))
    if changes := splat.get("pose_refinement"):
        rows.append(("splat pose refinement", _pose_refinement_summary(changes)))
    return rows
