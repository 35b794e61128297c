"""The splat optimiser's settings (:class:`OptimizeOptions`, with the ``brief`` preset, and the rasteriser's and
densification's, :class:`RasterOptions` and :class:`DensifyOptions`) and its result (:class:`OptimizeResult`); the
loop is :mod:`ffrecon.splat.optimize`.

No torch or numba here: every run builds these options (the splat's among a run's), and a run without the splat
should not load them."""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import TYPE_CHECKING

import numpy as np

from ffrecon.checks import check_number
from ffrecon.errors import InputError

if TYPE_CHECKING:
    from ffrecon.gaussians import Gaussians


@dataclass(frozen=True, kw_only=True)
class RasterOptions:
    tile_size: int = 16  # pixels; with the compiled kernels 16 beats 8 (73 vs 84 ms fwd+bwd, 60k Gaussians, 640x480)
    near: float = 0.01  # Gaussians whose centre has camera z below this are culled
    eps2d: float = 0.3  # pixels^2 added to the projected covariance (3DGS / gsplat default)

    def __post_init__(self) -> None:
        check_number("RasterOptions.tile_size", self.tile_size, low=1, integer=True)
        check_number("RasterOptions.near", self.near, low=0, low_open=True)
        check_number("RasterOptions.eps2d", self.eps2d, low=0)


@dataclass(frozen=True, kw_only=True)
class DensifyOptions:
    start_iteration: int = 100  # first densification (3DGS: 500 of 30k; brief runs start earlier)
    every: int = 100
    stop_fraction: float = 0.6  # no densification after this fraction of the budget
    grad_threshold: float = 0.0002  # mean view-space gradient norm (NDC units, as 3DGS)
    percent_dense: float = 0.01  # clone if largest scale <= this * scene scale, else split
    prune_opacity: float = 0.005
    max_world_size: float = 0.1  # prune Gaussians larger than this * scene scale (after the first round)

    def __post_init__(self) -> None:
        check_number("DensifyOptions.start_iteration", self.start_iteration, low=0, integer=True)
        check_number("DensifyOptions.every", self.every, low=1, integer=True)
        for name in ("stop_fraction", "prune_opacity"):
            check_number(f"DensifyOptions.{name}", getattr(self, name), low=0, high=1)
        for name in ("grad_threshold", "percent_dense"):
            check_number(f"DensifyOptions.{name}", getattr(self, name), low=0)
        check_number("DensifyOptions.max_world_size", self.max_world_size, low=0, low_open=True)


@dataclass(frozen=True, kw_only=True)
class OptimizeOptions:
    """Optimiser settings. The learning rates default to the ones of the 3DGS paper (Kerbl et al. 2023),
    tuned for ~30k iterations; :meth:`brief` scales them for the few hundred a CPU does in minutes.

    Adam (``torch.optim.Adam``, betas 0.9 and 0.999, eps 1e-15) has one learning rate per tensor:
    positions (times the scene scale), SH DC, SH rest, opacity, scales, rotations, with
    ``refine_poses`` the camera corrections and with ``appearance`` the per-image colour transforms.

    ``appearance``: each training image gets an affine colour transform ``[A | b]`` (``[3, 4]``)
    applied to its render before the loss, so that exposure and white-balance changes between photos
    are not baked into the Gaussians as floaters. The transforms average ``[I | 0]`` over the training
    images (the gauge: the Gaussians keep the mean exposure, and renders need no transform), and the
    loss adds ``appearance_weight * ||[A | b] - [I | 0]||^2`` of the image trained on. Measured on the
    demo scene (brief rates, 300 iterations, 1 thread, ``tools/bench_splat.py``): at its constant
    exposure, held-out PSNR 26.74 dB off and 26.71 dB on (26.62 and 26.64 with seed 1); with
    per-photo channel gains in [0.7, 1.3], colour-corrected held-out PSNR 24.62 dB off, 25.81 dB on.
    ``lr_appearance`` 2e-3 adds 0.14 dB to the latter but costs 0.14 dB at constant exposure."""

    iterations: int = 3000  # the plan: learning rates, resolution, SH and densification follow it
    # The splat stage's time budget (--splat-seconds): the optimisation's plan is compressed to fit what the
    # stage's other steps leave of it. The one default of the budget (brief() keeps it).
    max_seconds: float = 60.0
    # Coarse to fine: (fraction of the plan, downscale factor) from which that resolution is used.
    resolution_schedule: tuple[tuple[float, int], ...] = ((0.0, 1),)
    # Stop on a plateau of the training loss: once the plan is past ``plateau_after`` (full resolution,
    # densification over), stop when the mean loss of the last ``plateau_window`` iterations fell by
    # less than ``plateau_tolerance`` (relative) against the window before. 0 windows: never.
    plateau_window: int = 0
    plateau_tolerance: float = 0.002
    plateau_after: float = 0.6
    ssim_weight: float = 0.2  # loss = (1 - w) L1 + w (1 - SSIM), as 3DGS
    lr_means: float = 1.6e-4  # times the scene scale, decaying log-linearly to lr_means_final
    lr_means_final: float = 1.6e-6
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20
    lr_opacity: float = 5e-2
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    sh_degree: int = 3
    sh_band_every: int = 250  # switch on one more SH band every this many iterations
    densify: DensifyOptions | None = field(default_factory=DensifyOptions)
    max_gaussians: int = 100_000
    refine_poses: bool = False  # every training view's pose but the first's (``optimize(pose_views=...)``: some)
    lr_pose_rotation: float = 1e-4  # radians per step (the first training view stays fixed: gauge)
    lr_pose_translation: float = 1e-4  # times the scene scale
    # Bounds on each view's total correction: a camera further off than a few degrees is the evidence's
    # job (sfm.evidence), not the photometric loss's, which a wrong start drags into a wrong minimum.
    max_pose_rotation_deg: float = 5.0
    max_pose_translation: float = 0.05  # times the scene scale
    # The model's depth as a prior: loss += depth_weight * mean |rendered depth / prior depth - 1| over the
    # pixels where both are known (``optimize(depths=...)``; the splat stage passes them for few views).
    depth_weight: float = 0.2
    appearance: bool = True  # per-training-image affine colour transform (exposure, white balance)
    lr_appearance: float = 1e-3  # Adam rate of the colour transforms' entries (brief keeps it)
    appearance_weight: float = 1e-3  # pull of each transform towards [I | 0]
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    raster: RasterOptions = field(default_factory=RasterOptions)
    device: str = "cpu"  # "cuda" renders with gsplat (ffrecon.splat.render_gsplat)
    threads: int | None = None  # torch CPU threads while optimising; None: see cpu_threads()
    seed: int = 0
    progress: bool = True

    def __post_init__(self) -> None:
        check_number("OptimizeOptions.max_seconds", self.max_seconds, low=0, low_open=True, flag="--splat-seconds")
        check_number("OptimizeOptions.iterations", self.iterations, low=1, integer=True)
        for name in ("plateau_window", "sh_band_every"):
            check_number(f"OptimizeOptions.{name}", getattr(self, name), low=0, integer=True)
        check_number("OptimizeOptions.sh_degree", self.sh_degree, low=0, high=3, integer=True)
        check_number("OptimizeOptions.max_gaussians", self.max_gaussians, low=1, integer=True)
        check_number("OptimizeOptions.threads", self.threads, low=1, integer=True, allow_none=True)
        rates = [f.name for f in fields(self) if f.name.startswith("lr_")]  # 0 keeps that tensor as it is
        bounds = ("max_pose_rotation_deg", "max_pose_translation", "depth_weight")
        for name in (*rates, *bounds, "plateau_tolerance", "appearance_weight"):
            check_number(f"OptimizeOptions.{name}", getattr(self, name), low=0)
        for name in ("plateau_after", "ssim_weight"):
            check_number(f"OptimizeOptions.{name}", getattr(self, name), low=0, high=1)
        for start, factor in self.resolution_schedule:
            check_number("OptimizeOptions.resolution_schedule start", start, low=0, high=1)
            check_number("OptimizeOptions.resolution_schedule factor", factor, low=1, integer=True)
        if len(self.background) != 3:
            raise InputError(
                f"OptimizeOptions.background {self.background} is not an RGB triple",
                "set OptimizeOptions.background to (r, g, b), each in [0, 1]",
            )
        for value in self.background:
            check_number("OptimizeOptions.background", value, low=0, high=1)

    @staticmethod
    def brief(**overrides) -> OptimizeOptions:
        """Rates and schedule for runs of a few hundred to a thousand iterations: the 3DGS rates with
        positions and scales x10, SH x3, rotations x3 and opacity x2 (the final position rate stays
        3DGS's); a plan of 1500 iterations compressed into ``max_seconds``, trained at 1/4 resolution for
        the first 10 % of it, 1/2 until 30 %, full resolution after; one more SH band every 150
        iterations; stop early on a plateau of the training loss.

        Measured on a 24-view 640x480 scene like the demo's (``tools/bench_splat.py --optimize-only
        --width 640 --height 480 --seconds S``, 2 cores shared with other work): held-out PSNR 23.8 dB
        at S = 20, 25.3 at 30, 27.9-28.4 at 60, 32.3 at 150.

        Measured on the demo scene (60k Gaussians, 300 iterations, no densification): held-out
        PSNR 22.6 dB with only positions x10, 26.2 dB with this preset (26.7 dB with densification).

        Pose corrections at 5e-3 (rotation in radians, translation times the scene scale) per step, 50x
        3DGS-era rates: a few hundred steps must move a camera by the model's 2-3 deg. On the wide-baseline
        scene (tools/bench_sparse_splat.py, 20 s, 8 views) 3e-3 moved the cameras 0.3-1.0 deg and 1e-2 up
        to 3.8 deg (overshooting); the bounds (max_pose_*) cap the total either way.
        """
        base = OptimizeOptions()
        schedule = {
            "iterations": 1500,
            "resolution_schedule": ((0.0, 4), (0.1, 2), (0.3, 1)),
            "sh_band_every": 150,
            "plateau_window": 100,
        }
        rates = {
            "lr_means": base.lr_means * 10,
            "lr_scales": base.lr_scales * 10,
            "lr_sh_dc": base.lr_sh_dc * 3,
            "lr_sh_rest": base.lr_sh_rest * 3,
            "lr_quats": base.lr_quats * 3,
            "lr_opacity": base.lr_opacity * 2,
            "lr_pose_rotation": 5e-3,
            "lr_pose_translation": 5e-3,
        }
        return replace(base, **{**schedule, **rates, **overrides})


@dataclass(frozen=True)
class OptimizeResult:
    gaussians: Gaussians  # detached
    cam_from_world: np.ndarray  # [N, 3, 4] float64, refined where refine_poses (else the input)
    color_transforms: np.ndarray  # [N, 3, 4] float64 [A | b] per view: learnt where appearance, else [I | 0]
    iterations: int
    seconds: float  # optimisation time, callbacks excluded
    history: tuple[tuple[int, float, float], ...]  # (iteration, seconds, loss) every 10 iterations
    stop_reason: str = ""  # "plateau", "iterations" or "time budget"
    pose_views: tuple[int, ...] = ()  # the views whose poses were optimised
