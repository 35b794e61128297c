"""``ffrecon render OUT --camera-path PATH.json -o VIDEO.mp4``: a run's splat along a nerfstudio camera path.

The path (:mod:`ffrecon.formats.camera_path`) is in the world of the run's final cameras (``sparse/0``), as the
``camera_path.json`` every run writes beside ``flythrough.mp4`` and the one ``ffrecon view`` records. The frames
are rendered as the fly-through is (:func:`ffrecon.splat.video.render_camera_path`): with gsplat on CUDA when
it is there, else with ffrecon's CPU renderer; the background and rasteriser settings are the splat stage's
defaults.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path

from ffrecon.errors import InputError, OutputExistsError, ResourceError
from ffrecon.formats.camera_path import read_camera_path
from ffrecon.formats.splat_ply import read_splat_ply
from ffrecon.splat.optimize_options import OptimizeOptions
from ffrecon.splat.stage import SplatDevice, resolve_device
from ffrecon.splat.video import path_frames, render_camera_path

logger = logging.getLogger("ffrecon")

SPLAT_FILE = "splat.ply"


@dataclass(frozen=True)
class RenderedPath:
    """What :func:`render_path` wrote: the video, its frames, size and rate, the device and the seconds."""

    video: Path
    frames: int
    width: int
    height: int
    fps: float
    device: str
    seconds: float

    def summary(self) -> str:
        return (
            f"wrote {self.video}: {self.frames} frames, {self.width}x{self.height} at {self.fps:g} fps "
            f"({self.device}, {self.seconds:.1f} s)"
        )


def check_render_inputs(out_dir: Path, video: Path, *, overwrite: bool = False) -> Path:
    """The run's ``splat.ply``, after checking that ``video`` may be written; an :class:`InputError` (exit 2)
    or :class:`OutputExistsError` (exit 4) with the fix else. Nothing is written."""
    out_dir, video = Path(out_dir), Path(video)
    if not out_dir.is_dir():
        raise InputError(f"{out_dir} is not a folder", "pass the output folder of `ffrecon run ... -o OUT`")
    splat = out_dir / SPLAT_FILE
    if not splat.is_file():
        raise InputError(
            f"{out_dir} has no {SPLAT_FILE} to render",
            f"run `ffrecon run PHOTOS -o {out_dir} --resume` without --no-splat, or pass a run folder with a splat",
        )
    if video.suffix.lower() != ".mp4":
        raise InputError(f"-o {video} is not an .mp4 file", "pass -o VIDEO.mp4 (the video is MPEG-4, mp4v)")
    if video.is_dir():
        raise InputError(f"-o {video} is a folder", "pass -o VIDEO.mp4, a file name")
    if video.exists() and not overwrite:
        raise OutputExistsError(f"{video} exists", "pass --overwrite to replace it, or another -o")
    return splat


def render_path(
    out_dir: Path,
    camera_path: Path,
    video: Path,
    *,
    overwrite: bool = False,
    device: SplatDevice | str = SplatDevice.AUTO,
) -> RenderedPath:
    """Render the splat of the run folder ``out_dir`` along the camera path file ``camera_path`` into
    ``video`` (an ``.mp4``). Every input is checked before anything is rendered or written."""
    path = read_camera_path(camera_path)
    splat = check_render_inputs(out_dir, video, overwrite=overwrite)
    where = resolve_device(device)
    gaussians = read_splat_ply(splat)
    defaults = OptimizeOptions()  # the fly-through's background and rasteriser (the splat stage's defaults)
    start, video = time.perf_counter(), Path(video)
    video.parent.mkdir(parents=True, exist_ok=True)
    partial = video.with_name(f".{video.stem}.partial.mp4")  # an earlier video stays whole until the new one is
    try:
        written = render_camera_path(
            partial, gaussians, path, background=defaults.background, raster=defaults.raster, device=where
        )
        if written is not None:
            os.replace(partial, video)
    finally:
        partial.unlink(missing_ok=True)
    if written is None:
        raise ResourceError(
            f"OpenCV cannot write {video} on this system (no mp4v encoder)",
            "install an OpenCV build with video writing (the opencv-python wheel has it)",
        )
    frames = len(path_frames(path)[0])
    width, height = path.width - path.width % 2, path.height - path.height % 2
    return RenderedPath(Path(video), frames, width, height, path.fps, where, time.perf_counter() - start)
