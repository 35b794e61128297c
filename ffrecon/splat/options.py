"""The splat stage's options (:class:`SplatOptions`), the device it runs on, and what the pipeline knows per frame."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np

from ffrecon.checks import check_number
from ffrecon.errors import InputError
from ffrecon.splat.clean import CleanOptions
from ffrecon.splat.optimize_options import OptimizeOptions


class SplatDevice(enum.Enum):
    AUTO = "auto"  # CUDA + gsplat when both are available, else the CPU renderer
    CPU = "cpu"
    CUDA = "cuda"


@dataclass(frozen=True, kw_only=True)
class SplatOptions:
    """Settings of the splat stage; each setting lives in one place.

    The optimisation's settings (iterations, time budget, SH degree, Gaussian cap, pose refinement,
    exposure compensation, background, rasteriser, seed, CPU threads, progress bar, learning rates) are
    in ``optimize``, the cleaning's (crop box included) in ``clean``. ``optimize.device`` is not read:
    the stage resolves ``device`` (see :func:`resolve_device`) and gives the optimiser the result.
    """

    enabled: bool = True  # read by the pipeline (False: skip the stage); the functions here ignore it
    holdout_every: int = 8  # frames 0, k, 2k, ... are held out for evaluation; 0 = none
    max_seed_points: int = 60_000  # the seed is voxel-downsampled to at most this (and optimize.max_gaussians)
    video: bool = True  # flythrough.mp4 along a smooth path through the cameras
    spz: bool = True  # splat.spz (Niantic's SPZ, ~10x smaller) beside splat.ply; see ffrecon.formats.web
    sog: bool = False  # splat.sog (PlayCanvas) through splat-transform: opt-in, its CPU k-means is slow
    video_frames: int = 90
    report_views: int = 3  # held-out views rendered into renders/ for the report
    curve_every: int = 100  # score the held-out views every this many iterations (0: only at the end)
    compare_seeds: bool = False  # read by the pipeline: also train from COLMAP's points, same budget
    # Photometric pose refinement: the poses of the training frames the evidence did not confirm (passed as
    # ``pose_views``) are optimised with the Gaussians, within optimize's bounds; a frame whose render still
    # misses its photo by more than ``flag_psnr_drop_db`` below the median of the others is flagged.
    refine_unconfirmed_poses: bool = True
    flag_psnr_drop_db: float = 3.0
    # Fewer frames than this, and some frame unconfirmed: the model's depth is a prior in the loss
    # (optimize.depth_weight). Measured on the wide-baseline scene (docs/benchmarks.md): +0.5 dB held-out
    # PSNR with the model's cameras refined in the splat, -0.1 dB with bundle-adjusted cameras kept fixed.
    depth_prior_below: int = 12
    device: SplatDevice | str = SplatDevice.AUTO
    optimize: OptimizeOptions = field(default_factory=OptimizeOptions.brief)
    clean: CleanOptions = field(default_factory=CleanOptions)

    def __post_init__(self) -> None:
        check_number("SplatOptions.flag_psnr_drop_db", self.flag_psnr_drop_db, low=0)
        for name in ("holdout_every", "report_views", "curve_every", "depth_prior_below"):
            check_number(f"SplatOptions.{name}", getattr(self, name), low=0, integer=True)
        for name in ("max_seed_points", "video_frames"):
            check_number(f"SplatOptions.{name}", getattr(self, name), low=1, integer=True)


@dataclass(frozen=True)
class ViewPriors:
    """What the pipeline knows per frame beyond the photos: whose poses to refine, the model's depth."""

    pose_views: tuple[int, ...] = ()  # frames (indices into the views) whose poses the splat may correct
    depths: tuple[np.ndarray | None, ...] | None = None  # per frame [h, w] z-depth, 0 where unknown


def resolve_device(device: SplatDevice | str) -> str:
    """``"cuda"`` or ``"cpu"``: AUTO picks CUDA when CUDA and gsplat are both available."""
    from ffrecon.splat.render_gsplat import gsplat_available  # torch: here, where a device is chosen

    device = SplatDevice(device)
    if device is SplatDevice.CUDA and not gsplat_available():
        raise InputError(
            "device 'cuda' needs CUDA and gsplat", "install ffrecon[gpu] on a CUDA machine, or use device 'auto'"
        )
    return "cuda" if device is SplatDevice.CUDA or (device is SplatDevice.AUTO and gsplat_available()) else "cpu"
