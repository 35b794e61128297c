"""The splat stage's files: splat.ply, splat.spz and splat.sog, the held-out renders' PNGs, the fly-through."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from ffrecon.formats.camera_path import CAMERA_PATH_FILE
from ffrecon.splat.budget import budget_reason
from ffrecon.splat.options import SplatOptions
from ffrecon.types import PinholeCamera

if TYPE_CHECKING:
    import torch

    from ffrecon.gaussians import Gaussians
    from ffrecon.splat.stage_run import StageRun

logger = logging.getLogger("ffrecon.splat")

# What the stage writes, relative to the run folder (a resumed or replaced run removes them first); the
# fly-through's camera path (camera_path.json) is written beside flythrough.mp4.
OUTPUTS = ("splat.ply", "splat.spz", "splat.sog", "renders", "flythrough.mp4", CAMERA_PATH_FILE)


MIN_VIDEO_FRAMES = 15  # the budget shortens the fly-through to no fewer frames (it is an output the README promises)


def write_png(path: Path, rgb: torch.Tensor | np.ndarray) -> Path:
    arr = rgb if isinstance(rgb, np.ndarray) else (rgb.numpy() * 255 + 0.5).astype(np.uint8)
    cv2.imwrite(str(path), cv2.cvtColor(arr, cv2.COLOR_RGB2BGR))
    return path


def write_outputs(
    out_dir: Path,
    cleaned: Gaussians,
    poses: np.ndarray,
    camera: PinholeCamera,
    options: SplatOptions,
    run: StageRun,
) -> tuple[Path, Path | None, dict[str, Path | None]]:
    """``splat.ply``, (when ``options.video`` and the stage's budget allow) ``flythrough.mp4`` and the web
    formats asked for (``{"spz_path": ..., "sog_path": ...}``, see :mod:`ffrecon.formats.web`; splat.spz when
    the budget allows, splat.sog, opt-in, whatever it takes); adds their times to ``run.timer``."""
    from ffrecon.formats.splat_ply import write_splat_ply  # these load torch and numba: here, so that OUTPUTS does not
    from ffrecon.formats.web import WebExportError, write_sog, write_splat_spz
    from ffrecon.splat.video import write_flythrough

    o, timer = options.optimize, run.timer
    with timer.stage("write_ply"):
        ply_path = write_splat_ply(out_dir / "splat.ply", cleaned, sh_degree=o.sh_degree)
    web_paths: dict[str, Path | None] = {"spz_path": None, "sog_path": None}
    if options.spz:  # a promised output, and cheap (0.04-0.33 s): written even when the plan had no room for it
        run.skipped.pop("write_spz", None)
        with timer.stage("write_spz"):
            web_paths["spz_path"] = write_splat_spz(out_dir / "splat.spz", cleaned, sh_degree=o.sh_degree)
    if options.sog:
        with timer.stage("write_sog"):
            try:
                web_paths["sog_path"] = write_sog(ply_path, out_dir / "splat.sog")
            except WebExportError as err:  # an optional extra: the splat itself is written, say why not this
                logger.warning("splat.sog not written: %s", err)
    frames = _video_frames(run, options) if options.video else 0
    if not frames:
        return ply_path, None, web_paths
    with timer.stage("video"):
        video_path = write_flythrough(
            out_dir / "flythrough.mp4",
            cleaned,
            poses,
            camera,
            num_frames=frames,
            background=o.background,
            raster=o.raster,
            device=o.device,
        )
    return ply_path, video_path, web_paths


def _video_frames(run: StageRun, options: SplatOptions) -> int:
    """The fly-through's frames: ``options.video_frames``, fewer when the stage's budget has room for fewer, but
    never under ``MIN_VIDEO_FRAMES`` (flythrough.mp4 is a promised output: a short one over budget rather than
    none); said in ``run.skipped``. Only the video is shortened: it is the last step, so nothing after it needs
    time."""
    per_frame = next((s.seconds for s in run.after.steps if s.name == "video"), 0.0) / options.video_frames
    fit = int(run.budget.left() / per_frame) if per_frame > 0 else options.video_frames
    run.skipped.pop("video", None)  # left out of the plan, it still runs when the optimiser left time for it
    if fit >= options.video_frames:
        return options.video_frames
    why = budget_reason(options.video_frames * per_frame, run.budget.left(), run.budget.seconds, "when it was due")
    fit = min(max(fit, MIN_VIDEO_FRAMES), options.video_frames)
    run.skipped["video"] = f"shortened to {fit} of {options.video_frames} frames: {why}"
    return fit
