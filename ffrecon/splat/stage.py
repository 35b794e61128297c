"""The splat stage: seed, optimise briefly, clean, export, measure.

Two entries share one implementation. :func:`run_splat_from_prediction` (what the pipeline calls)
seeds from the feed-forward depth maps of the training views; :func:`run_splat` takes an explicit
seed cloud. Both write, under ``out_dir``: ``splat.ply`` (3DGS layout, see :mod:`ffrecon.formats.splat_ply`),
``renders/<view>_{truth,seed,splat}.png`` for a few held-out views and ``flythrough.mp4``.

The held-out views (every ``holdout_every``-th frame, starting with the first) are chosen once, by
:func:`split_views`, in each entry: they are never trained on nor seeded from, and PSNR and SSIM
are measured on them for the seed, the optimised and the cleaned (exported) splat. The cleaned
splat is also scored after a colour correction, as is usual for photos whose exposure and white
balance vary: an affine colour transform from its render to the held-out photo, fitted by least
squares on that photo (see :func:`ffrecon.splat.appearance.fit_color_transform`), so that a
held-out frame's own exposure, which no training image shows, does not count as an error.
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import cv2
import numpy as np
import torch

from ffrecon.capture import CaptureOptions
from ffrecon.checks import check_number, check_shape, require_finite
from ffrecon.errors import InputError
from ffrecon.formats.splat_ply import write_splat_ply
from ffrecon.formats.web import WebExportError, write_sog, write_splat_spz
from ffrecon.gaussians import Gaussians
from ffrecon.geometry.poses import camera_centers
from ffrecon.geometry.rotations import rotation_angle_deg
from ffrecon.splat.appearance import apply_color_transform, fit_color_transform
from ffrecon.splat.budget import (
    AfterSteps,
    StageBudget,
    Step,
    ViewCosts,
    after_steps,
    budget_reason,
    plan_budget,
)
from ffrecon.splat.clean import CleanOptions, CleanReport, clean_gaussians
from ffrecon.splat.memory import splat_peak_bytes, training_side
from ffrecon.splat.optimize import (
    OptimizeOptions,
    OptimizeResult,
    cpu_threads,
    optimize,
    scene_scale,
    torch_threads,
    unit_float,
)
from ffrecon.splat.render import warm_up
from ffrecon.splat.render_gsplat import gsplat_available, render_view_on
from ffrecon.splat.seed import initial_gaussians, reduce_points, seed_from_prediction
from ffrecon.splat.ssim import ssim_mean
from ffrecon.splat.video import write_flythrough
from ffrecon.timing import StageTimer, Timings, cpu_seconds
from ffrecon.types import PinholeCamera, Prediction, capped_size

logger = logging.getLogger("ffrecon.splat")


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
class ViewMetrics:
    """PSNR (dB) and SSIM of one held-out view; ``*_color_corrected`` after :func:`color_corrected`."""

    name: str
    psnr_seed: float
    ssim_seed: float
    psnr_optimized: float
    ssim_optimized: float
    psnr_cleaned: float
    ssim_cleaned: float
    psnr_cleaned_color_corrected: float
    ssim_cleaned_color_corrected: float

    KEYS: ClassVar[tuple[str, ...]] = (
        "psnr_seed",
        "ssim_seed",
        "psnr_optimized",
        "ssim_optimized",
        "psnr_cleaned",
        "ssim_cleaned",
        "psnr_cleaned_color_corrected",
        "ssim_cleaned_color_corrected",
    )


@dataclass(frozen=True)
class PoseChange:
    """What the photometric pose refinement did to one training frame's camera."""

    name: str
    rotation_deg: float  # the correction's angle
    translation: float  # the camera centre's move, as a fraction of the scene scale
    psnr: float  # its photo against its render after the optimisation (a training view: fit, not held-out)
    flagged: bool  # psnr more than SplatOptions.flag_psnr_drop_db below the median of the frames kept fixed

    def to_report(self) -> dict:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class ViewPriors:
    """What the pipeline knows per frame beyond the photos: whose poses to refine, the model's depth."""

    pose_views: tuple[int, ...] = ()  # frames (indices into the views) whose poses the splat may correct
    depths: tuple[np.ndarray | None, ...] | None = None  # per frame [h, w] z-depth, 0 where unknown


@dataclass(frozen=True)
class SplatResult:
    out_dir: Path
    ply_path: Path
    renders_dir: Path
    render_paths: tuple[tuple[str, Path, Path, Path], ...]  # (view, truth, seed, splat) PNGs
    video_path: Path | None
    train: tuple[int, ...]  # frame indices optimised on (and, from a prediction, seeded from)
    heldout: tuple[int, ...]  # frame indices held out for evaluation
    heldout_metrics: tuple[ViewMetrics, ...]  # one per held-out frame, in the order of `heldout`
    timings: Timings  # wall and CPU seconds per step of the whole stage (they sum to its wall clock)
    iterations: int
    iterations_per_second: float
    count_seed: int
    count_optimized: int  # before cleaning
    count_cleaned: int  # written to splat.ply
    clean: CleanReport
    backend: str  # "cpu" (ffrecon's renderer) or "gsplat"
    cam_from_world: np.ndarray = field(repr=False)  # [N, 3, 4] the cameras used (refined when refine_poses)
    # [N, 3, 4] float64 [A | b] per frame, the learnt exposure/white-balance compensation of the training
    # frames (optimize.appearance); [I | 0] for held-out frames and without it. Not part of splat.ply.
    color_transforms: np.ndarray = field(repr=False)
    # (iteration, optimisation seconds, mean held-out PSNR dB, SSIM) every ``curve_every`` iterations,
    # from the seed (iteration 0) on; plain renders of the uncleaned splat. Empty when not asked for.
    heldout_curve: tuple[tuple[int, float, float, float], ...] = ()
    stop_reason: str = ""  # what ended the optimisation: "plateau", "iterations" or "time budget"
    spz_path: Path | None = None  # splat.spz, the same splat in Niantic's SPZ (options.spz)
    sog_path: Path | None = None  # splat.sog, PlayCanvas's SOG (options.sog)
    max_side: int | None = None  # views longer than this (px) were shrunk to it to fit memory (splat.memory)
    pose_changes: tuple[PoseChange, ...] = ()  # one per frame whose pose the splat refined
    depth_prior: bool = False  # whether the model's depth was a prior in the loss
    budget_s: float | None = None  # the stage's time budget (optimize.max_seconds, --splat-seconds)
    skipped_steps: tuple[tuple[str, str], ...] = ()  # (step, why) the budget left out or shortened

    def mean(self, key: str) -> float:
        """Mean over held-out views of a :class:`ViewMetrics` field (nan without held-out views)."""
        values = [getattr(v, key) for v in self.heldout_metrics]
        return float(np.mean(values)) if values else float("nan")

    def report_images(self) -> list[tuple[str, Path]]:
        """``(caption, PNG path)`` for report.html: per reported held-out view, truth, seed and splat."""
        by_name = {v.name: v for v in self.heldout_metrics}
        out = []
        for name, truth, seed, splat in self.render_paths:
            m = by_name[name]
            out += [
                (f"{name}: ground truth", truth),
                (f"{name}: seed, PSNR {m.psnr_seed:.1f} dB", seed),
                (f"{name}: splat, PSNR {m.psnr_cleaned:.1f} dB", splat),
            ]
        return out

    def to_report(self) -> dict:
        """JSON-serialisable section for report.json; paths relative to ``out_dir``."""

        def rel(p: Path | None) -> str | None:
            return None if p is None else str(Path(p).relative_to(self.out_dir))

        keys = ViewMetrics.KEYS
        return {
            "backend": self.backend,
            "max_side": self.max_side,
            "splat_ply": rel(self.ply_path),
            "splat_spz": rel(self.spz_path),
            "splat_sog": rel(self.sog_path),
            "renders": [
                {"view": v, "truth": rel(t), "seed": rel(s), "splat": rel(o)} for v, t, s, o in self.render_paths
            ],
            "video": rel(self.video_path),
            "heldout_views": [v.name for v in self.heldout_metrics],
            "heldout_mean": {k: (None if np.isnan(self.mean(k)) else self.mean(k)) for k in keys},
            "heldout_per_view": [{"name": v.name, **{k: getattr(v, k) for k in keys}} for v in self.heldout_metrics],
            "iterations": self.iterations,
            "iterations_per_second": self.iterations_per_second,
            "stop_reason": self.stop_reason,
            "gaussians": {"seed": self.count_seed, "optimized": self.count_optimized, "cleaned": self.count_cleaned},
            "cleaning": self.clean.to_dict(),
            "timings_s": self.timings.to_report(),
            "cpu_s": self.timings.cpu_report(),
            "budget_s": self.budget_s,
            "skipped_steps": dict(self.skipped_steps),
            "heldout_curve": [
                {"iteration": i, "seconds": t, "psnr": p, "ssim": q} for i, t, p, q in self.heldout_curve
            ],
            "pose_refinement": [c.to_report() for c in self.pose_changes],
            "depth_prior": self.depth_prior,
        }


def image_metrics(rendered: torch.Tensor, truth: torch.Tensor) -> tuple[float, float]:
    """PSNR (dB) and SSIM of ``[H, W, 3]`` images in [0, 1]; a ``[H, W, 4]`` ``truth`` carries a mask (1 use,
    0 ignore) in its 4th channel: the PSNR is of the pixels used, the SSIM of the render with the truth's
    own colour where the mask is 0.

    SSIM as the 3DGS evaluation computes it (11x11 Gaussian window, sigma 1.5, zero padding), with the
    training loss's compiled kernel (:func:`~ffrecon.splat.ssim.ssim_mean`; it matches kornia's SSIM
    inside the 5-pixel border, where kornia reflects instead, tests/splat/test_optimize.py): 43 ms a
    640x480 view against kornia's 117 ms, and the held-out views are scored every 100 iterations.
    """
    rendered = rendered.detach().clamp(0, 1)
    weight = torch.ones_like(rendered[..., :1])
    if truth.shape[-1] == 4:
        weight, truth = truth[..., 3:].float(), truth[..., :3]
        rendered = weight * rendered + (1 - weight) * truth
    a = rendered.permute(2, 0, 1).float()
    b = truth.permute(2, 0, 1).float()
    mse = float(((a - b) ** 2 * weight.permute(2, 0, 1)).sum() / (3 * weight.sum()).clamp_min(1e-9))
    psnr = 10 * np.log10(1.0 / max(mse, 1e-12))
    with torch.no_grad():
        ssim = float(ssim_mean(a.contiguous(), b.contiguous()))
    return float(psnr), ssim


def color_corrected(rendered: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """``rendered [H, W, 3]`` (clamped to [0, 1]) after the affine colour transform that best maps it to
    ``truth [H, W, 3]`` (see :func:`~ffrecon.splat.appearance.fit_color_transform`), clamped to [0, 1];
    float32.

    >>> truth = torch.rand(8, 8, 3, generator=torch.Generator().manual_seed(0))
    >>> bool(torch.allclose(color_corrected(0.8 * truth + 0.05, truth), truth, atol=1e-3))
    True
    """
    source = rendered.clamp(0, 1)
    if truth.shape[-1] == 4:  # a mask in the 4th channel: fit on the pixels used
        used = truth[..., 3] > 0.5
        transform = fit_color_transform(source.detach()[used], truth[..., :3][used]).to(source)
        return apply_color_transform(source, transform).clamp(0, 1)
    transform = fit_color_transform(source, truth).to(source)
    return apply_color_transform(source, transform).clamp(0, 1)


def with_masks(images: Sequence[np.ndarray], masks: Sequence[np.ndarray] | None) -> list[np.ndarray]:
    """``[H, W, 4]`` uint8: each RGB image with its mask (255 use, 0 ignore) as a 4th channel, which the loss
    and the scores read (:func:`~ffrecon.splat.optimize.photometric_loss`, :func:`image_metrics`); the
    images as they are without masks."""
    if masks is None:
        return list(images)
    return [np.dstack([im, np.where(m, 255, 0).astype(np.uint8)]) for im, m in zip(images, masks)]


def split_views(num: int, holdout_every: int) -> tuple[list[int], list[int]]:
    """``(train, heldout)`` indices: every ``holdout_every``-th frame from 0 is held out (none if 0 or
    if that would leave no training view).

    >>> split_views(10, 8)
    ([1, 2, 3, 4, 5, 6, 7, 9], [0, 8])
    """
    test = [i for i in range(num) if holdout_every > 0 and i % holdout_every == 0]
    train = [i for i in range(num) if i not in test]
    return (train, test) if train else (list(range(num)), [])


def resolve_device(device: SplatDevice | str) -> str:
    """``"cuda"`` or ``"cpu"``: AUTO picks CUDA when CUDA and gsplat are both available."""
    device = SplatDevice(device)
    if device is SplatDevice.CUDA and not gsplat_available():
        raise InputError(
            "device 'cuda' needs CUDA and gsplat", "install ffrecon[gpu] on a CUDA machine, or use device 'auto'"
        )
    return "cuda" if device is SplatDevice.CUDA or (device is SplatDevice.AUTO and gsplat_available()) else "cpu"


OUTPUTS = ("splat.ply", "splat.spz", "splat.sog", "renders", "flythrough.mp4")  # relative to the run folder


def check_splat_fits(sizes_wh: Sequence[tuple[int, int]], options: SplatOptions) -> None:
    """Refuse, before any pose is made, a splat that cannot fit in memory at all (when the splat is on)."""
    if options.enabled:
        check_splat_memory(sizes_wh, options, when=" (planned)")


def check_splat_memory(sizes_wh: Sequence[tuple[int, int]], options: SplatOptions, *, when: str = "") -> int | None:
    """The long side (px) to which the CPU splat shrinks larger views of ``sizes_wh`` to fit the memory free
    now (None: full size; :mod:`ffrecon.splat.memory`), logged when it shrinks any. The pipeline asks before
    any work, so that a splat that cannot fit at all is a :class:`~ffrecon.errors.ResourceError` in seconds;
    the stage asks again when it starts, with the memory free then. On CUDA (gsplat): None."""
    if not sizes_wh or resolve_device(options.device) != "cpu":
        return None
    side = training_side(sizes_wh, options.optimize.max_gaussians)
    if side is not None:
        w, h = max(sizes_wh, key=lambda s: s[0] * s[1])
        full = splat_peak_bytes(sizes_wh, options.optimize.max_gaussians)
        shrunk = sum(max(s) > side for s in sizes_wh)
        logger.warning(
            "splat%s: training %d view(s) at %d px on the long side (%dx%d instead of %dx%d): full size needs "
            "about %.1f GB, more than memory allows; smaller frames (--max-image-size, default %s) avoid this",
            when,
            shrunk,
            side,
            *capped_size(w, h, side),
            w,
            h,
            full / 2**30,
            CaptureOptions.__dataclass_fields__["max_image_size"].default,
        )
    return side


def _capped(images, cameras, max_side: int | None) -> tuple[list[np.ndarray], list[PinholeCamera]]:
    """Views whose long side exceeds ``max_side`` shrunk to it (area average), their cameras scaled to the
    new pixel grid; the others as they are."""
    out_images, out_cameras = [], []
    for im, cam in zip(images, cameras):
        w, h = capped_size(im.shape[1], im.shape[0], max_side)
        if (w, h) != (im.shape[1], im.shape[0]):
            cam = cam.scaled(w / im.shape[1], h / im.shape[0])
            im = cv2.resize(im, (w, h), interpolation=cv2.INTER_AREA)
        out_images.append(im)
        out_cameras.append(cam)
    return out_images, out_cameras


def run_splat(
    images: Sequence[np.ndarray],
    names: Sequence[str],
    cam_from_world: np.ndarray,
    cameras: Sequence[PinholeCamera],
    seed_xyz: np.ndarray,
    seed_rgb: np.ndarray,
    options: SplatOptions,
    out_dir: Path,
    *,
    masks: Sequence[np.ndarray] | None = None,
    timer: StageTimer | None = None,
) -> SplatResult:
    """Optimise, clean and export a Gaussian splat from an explicit seed; measure it on held-out views.

    Args:
        images: per frame ``[H, W, 3]`` uint8 RGB.
        names: per frame file names (held-out renders are named after their stem).
        cam_from_world: ``[N, 3, 4]`` OpenCV poses; cameras: per frame pinhole intrinsics.
        seed_xyz: ``[M, 3]`` world points; seed_rgb: ``[M, 3]`` float colours in [0, 1]. To keep the
            held-out PSNR honest, they should come from the training views of :func:`split_views` only.
        masks: per frame ``[H, W]`` bool (True: use the pixel; ``--masks``), or None: the loss and the held-out
            scores ignore the pixels they leave out.
        timer: the stage's timer when the caller's work (reading the photos) belongs to it: the stage's time
            budget (``optimize.max_seconds``) counts from when it was made. None: from now.
    """
    timer = timer or StageTimer()
    images = with_masks(images, masks)
    split = split_views(len(images), options.holdout_every)
    with torch_threads(cpu_threads(options.optimize.threads)):
        return _splat(images, names, cam_from_world, cameras, seed_xyz, seed_rgb, split, options, out_dir, timer)


def run_splat_from_prediction(
    prediction: Prediction,
    images: Sequence[np.ndarray],
    cam_from_world: np.ndarray,
    cameras: Sequence[PinholeCamera],
    options: SplatOptions,
    out_dir: Path,
    *,
    unconfirmed: Sequence[int] = (),
    masks: Sequence[np.ndarray] | None = None,
    timer: StageTimer | None = None,
) -> SplatResult:
    """The splat stage seeded from feed-forward depth: split the views, seed from the training views, optimise.

    Args:
        prediction: the feed-forward output (depth maps, confidences, names) for the same frames.
        images: per frame ``[H, W, 3]`` uint8 RGB at the size of ``cameras``.
        cam_from_world: ``[N, 3, 4]`` OpenCV poses and cameras: per frame intrinsics, the final ones
            (e.g. after bundle adjustment), in the prediction's world frame and scale.
        unconfirmed: frames no independent evidence confirmed: with ``refine_unconfirmed_poses`` their
            training views' poses are optimised with the Gaussians (and reported, see :class:`PoseChange`).

    Each training view's depth map is unprojected with its final camera (see :func:`prediction_seed`),
    then :func:`run_splat`'s optimisation follows with the same split. With fewer than
    ``depth_prior_below`` frames and some frame unconfirmed, the depth maps are also a prior in the loss
    (``optimize.depth_weight``). ``timer``: as :func:`run_splat`'s.
    """
    timer = timer or StageTimer()
    images = with_masks(images, masks)  # the prediction's depth is already masked (no seed from there)
    split = split_views(len(images), options.holdout_every)
    _validate_views(images, prediction.names, cam_from_world, cameras)
    with torch_threads(cpu_threads(options.optimize.threads)):
        with timer.stage("fuse_depth"):
            xyz, rgb = prediction_seed(prediction, images, cam_from_world, cameras, split[0], options)
        names = prediction.names
        pose_views = tuple(unconfirmed) if options.refine_unconfirmed_poses else ()
        few = len(images) < options.depth_prior_below
        priors = ViewPriors(pose_views, _depth_priors(prediction) if few and unconfirmed else None)
        return _splat(images, names, cam_from_world, cameras, xyz, rgb, split, options, out_dir, timer, priors)


def _depth_priors(prediction: Prediction, min_conf: float = 1.0) -> tuple[np.ndarray, ...]:
    """Per frame the model's depth where it is known and confident (the seed's rule), 0 elsewhere."""
    return tuple(
        np.where(prediction.valid_mask(k, min_conf), d, 0).astype(np.float32) for k, d in enumerate(prediction.depth)
    )


def prediction_seed(
    prediction: Prediction,
    images: Sequence[np.ndarray],
    cam_from_world: np.ndarray,
    cameras: Sequence[PinholeCamera],
    frames: Sequence[int],
    options: SplatOptions,
) -> tuple[np.ndarray, np.ndarray]:
    """Seed points from the depth maps of ``frames``, placed with the final cameras.

    Final (refined) cameras sit in the feed-forward world at its scale, so each depth map is
    unprojected with its frame's final pose and intrinsics: points from different frames then agree
    where the feed-forward poses did not. Images are resized (``INTER_AREA``) to their depth map's
    grid where the sizes differ. Returns ``(xyz [M, 3] float64, rgb [M, 3] float32 in [0, 1])``.
    """
    pred = dataclasses.replace(prediction, cam_from_world=cam_from_world, cameras=tuple(cameras))
    small = [
        im[..., :3] if im.shape[:2] == d.shape else cv2.resize(im[..., :3], d.shape[::-1], interpolation=cv2.INTER_AREA)
        for im, d in zip(images, pred.depth)
    ]
    return seed_from_prediction(
        pred, small, max_points=options.max_seed_points, frames=frames, seed=options.optimize.seed
    )


@dataclass
class _Run:
    """What the stage's steps share: its timer and budget, the steps after the optimiser at work (see
    :class:`~ffrecon.splat.budget.AfterSteps`), why steps were left out, the held-out curve, and the held-out
    scores already known (``(iteration, view) -> (psnr, ssim)``; the seed's renders of the report views)."""

    timer: StageTimer
    budget: StageBudget
    costs: ViewCosts = ViewCosts(0.0, 0.0)
    after: AfterSteps | None = None
    skipped: dict[str, str] = field(default_factory=dict)
    curve: list[tuple[int, float, float, float]] = field(default_factory=list)
    curve_timer: StageTimer = field(default_factory=StageTimer)
    curve_every: int = 0  # iterations between the held-out curve's points (0: no curve)
    known: dict[tuple[int, int], tuple[float, float]] = field(default_factory=dict)
    seed_renders: dict[int, torch.Tensor] = field(default_factory=dict)
    # The optimiser's deadline is the budget's less ``reserve``, the seconds the steps after it kept by the plan
    # (``kept``) are estimated to take; ``estimate(gaussians)`` re-estimates them (the curve's points do).
    reserve: float = 0.0
    kept: tuple[str, ...] = ()
    estimate: Callable[[int], list[Step]] | None = None

    def reestimate(self, gaussians: int) -> None:
        if self.estimate is not None:
            self.reserve = sum(s.seconds for s in self.estimate(gaussians) if s.name in self.kept)

    def optimizer_deadline(self) -> float:
        return self.budget.deadline - self.reserve


CURVE_SHARE = 0.15  # the held-out curve's points stop once they would take more of the stage's budget than this
MIN_VIDEO_FRAMES = 15  # the budget shortens the fly-through to no fewer frames (it is an output the README promises)


def _splat(
    images,
    names,
    cam_from_world,
    cameras,
    seed_xyz,
    seed_rgb,
    split,
    options: SplatOptions,
    out_dir,
    timer: StageTimer,
    priors: ViewPriors = ViewPriors(),
) -> SplatResult:
    """Both entries' implementation, from the seed cloud and the ``(train, heldout)`` split on.

    ``timer`` holds what the entry already measured and receives the rest of the steps; the stage's budget
    (``options.optimize.max_seconds``) counts from when it was made."""
    _validate_views(images, names, cam_from_world, cameras, seed=(seed_xyz, seed_rgb))
    train, heldout = split
    out_dir = Path(out_dir)
    options, max_side, images, cameras = _on_device(options, images, cameras, split)
    run = _Run(timer, StageBudget(options.optimize.max_seconds, timer.started))
    seed, result, cleaned, clean_report = _fit_and_clean(
        images, cam_from_world, cameras, seed_xyz, seed_rgb, split, options, run, priors
    )
    poses = result.cam_from_world
    changes = _pose_check(timer, names, images, cam_from_world, cameras, result, split, options)
    splats = {"seed": seed, "optimized": result.gaussians, "cleaned": cleaned}
    known = (_known_scores(run, heldout, result.iterations), run.seed_renders)  # scored by the held-out curve
    with timer.stage("evaluate"):
        metrics, renders = _evaluate_heldout(
            heldout, names, images, poses, cameras, splats, options, out_dir, known=known
        )
    ply_path, video_path, web_paths = _write_outputs(out_dir, cleaned, poses, cameras[0], options, run)
    timer.close()  # what no step holds (validation, the result itself): the steps sum to the stage
    res = SplatResult(
        out_dir=out_dir,
        ply_path=ply_path,
        renders_dir=out_dir / "renders",
        render_paths=renders,
        video_path=video_path,
        train=tuple(train),
        heldout=tuple(heldout),
        heldout_metrics=metrics,
        timings=timer.freeze(),
        iterations=result.iterations,
        iterations_per_second=result.iterations / max(result.seconds, 1e-9),
        count_seed=len(seed),
        count_optimized=len(result.gaussians),
        count_cleaned=len(cleaned),
        clean=clean_report,
        backend="gsplat" if options.optimize.device == "cuda" else "cpu",
        cam_from_world=poses,
        color_transforms=result.color_transforms,
        heldout_curve=tuple(run.curve),
        stop_reason=result.stop_reason,
        max_side=max_side,
        pose_changes=changes,
        depth_prior=priors.depths is not None and options.optimize.depth_weight > 0,
        budget_s=run.budget.seconds,
        skipped_steps=tuple(run.skipped.items()),
        **web_paths,
    )
    return _log_summary(res)


def _on_device(options: SplatOptions, images, cameras, split) -> tuple[SplatOptions, int | None, list, list]:
    """``(options, max_side, images, cameras)``: the options with the device the splat trains and renders on,
    and the views shrunk to what memory allows (see :func:`check_splat_memory`)."""
    device = resolve_device(options.device)  # training and every later render (scores, renders, video)
    options = dataclasses.replace(options, optimize=dataclasses.replace(options.optimize, device=device))
    logger.info("splat: %d training and %d held-out views, device %s", len(split[0]), len(split[1]), device)
    max_side = check_splat_memory([(im.shape[1], im.shape[0]) for im in images], options)
    return (options, max_side, *_capped(images, cameras, max_side))


def _known_scores(run: _Run, heldout, iterations: int) -> dict[tuple[str, int], tuple[float, float]]:
    """The held-out scores of the seed and of the optimised splat the curve already measured."""
    known = {("seed", i): run.known[0, i] for i in heldout if (0, i) in run.known}
    return known | {("optimized", i): run.known[iterations, i] for i in heldout if (iterations, i) in run.known}


def _fit_and_clean(
    images, cam_from_world, cameras, seed_xyz, seed_rgb, split, options: SplatOptions, run: _Run, priors: ViewPriors
) -> tuple[Gaussians, OptimizeResult, Gaussians, CleanReport]:
    """Seed Gaussians, optimise them on the training views within what the stage's budget leaves after the
    steps to come, clean the result; adds the step times to ``run.timer`` and, with ``options.curve_every``,
    the held-out scores over the optimisation to ``run.curve``."""
    train, heldout = split
    opt, timer = options.optimize, run.timer
    cam_from_world = np.asarray(cam_from_world, np.float64)
    with timer.stage("seed"):
        seed, seed_points = _initial_splat(seed_xyz, seed_rgb, options)
        scale = scene_scale(cam_from_world[train], seed_points)
    targets = [torch.from_numpy(np.ascontiguousarray(im)) for im in images]  # uint8, as the photos (unit_float)
    if opt.device == "cpu":
        with timer.stage("compile"):  # numba's kernels: compiled on first use, then loaded from its cache
            warm_up()
    score = _scorer(run, heldout, cameras, targets, options) if options.curve_every > 0 and heldout else None
    run.curve_every = options.curve_every if score is not None else 0
    if score is not None:
        score(0, 0.0, seed, cam_from_world)  # also measures a view's render and score for the budget
    else:
        with timer.stage("budget_probe"):
            run.costs = _probe(seed, cam_from_world, cameras, (heldout or train)[0], targets, opt)
    _plan(run, len(seed), split, options, priors, curve=score is not None)
    result = _optimize_timed(run, seed, targets, cam_from_world, cameras, split, opt, scale, score, priors)
    if score is not None and run.curve[-1][0] < result.iterations and run.after.allowed("heldout_curve"):
        score(result.iterations, result.seconds, result.gaussians, result.cam_from_world)  # ends where it did
    curve = run.curve_timer.freeze()
    timer.add("heldout_curve", curve.total_s, sum(c for c in curve.cpu if c is not None))
    run.after.update(_after(run, len(result.gaussians), split, options, priors, curve=score is not None))
    logger.debug("splat: the steps after the optimiser, estimated: %s", {s.name: s.seconds for s in run.after.steps})
    poses = result.cam_from_world
    with timer.stage("clean"):
        optimized = [run.known.get((result.iterations, i), (None,))[0] for i in heldout]
        first = float(np.mean(optimized)) if heldout and None not in optimized else None
        judged = heldout and run.after.allowed("clean_judge")
        judge = _heldout_psnr(heldout, poses, cameras, targets, opt, first) if judged else None
        train_cameras = [cameras[i] for i in train]
        cleaned, report = clean_gaussians(result.gaussians, poses[train], train_cameras, options.clean, judge=judge)
    return seed, result, cleaned, report


def _after(run: _Run, gaussians: int, split, options: SplatOptions, priors: ViewPriors, *, curve: bool) -> list:
    """The steps after the optimiser with their seconds estimated from ``run.costs`` (see
    :func:`~ffrecon.splat.budget.after_steps`)."""
    refined = len(priors.pose_views) if options.refine_unconfirmed_poses else 0
    return after_steps(
        run.costs,
        gaussians=gaussians,
        heldout=len(split[1]),
        pose_views=refined,
        video_frames=options.video_frames if options.video else 0,
        spz=options.spz,
        curve=curve,
    )


def _plan(run: _Run, seed_count: int, split, options: SplatOptions, priors: ViewPriors, *, curve: bool) -> None:
    """Split what the stage's budget leaves after the steps so far between the optimiser and the estimated
    steps after it (optional ones left out when they would take more than half of it): sets ``run.reserve``,
    ``run.kept``, ``run.estimate`` and ``run.after``. The splat may grow to ``optimize.max_gaussians``: the
    first estimate assumes renders slow down with it (the seed's own render, measured, is slower than a
    trained splat's: its Gaussians are larger); the held-out curve's points measure them again."""
    o = options.optimize
    grown = o.max_gaussians if o.densify is not None else seed_count
    factor = 1.0 + 0.25 * np.log2(max(1.0, grown / max(seed_count, 1)))
    run.estimate = lambda count: _after(run, count, split, options, priors, curve=curve)
    measured = run.costs
    run.costs = ViewCosts(measured.render_s * factor, measured.score_s)
    steps = run.estimate(grown)
    run.costs = measured
    plan = plan_budget(run.budget.seconds, run.timer.elapsed(), steps)
    run.skipped.update(plan.skipped)
    run.after = AfterSteps(run.budget, steps, run.skipped)
    run.kept = plan.kept
    run.reserve = sum(s.seconds for s in steps if s.name in plan.kept)
    logger.info(
        "splat: %.1f s of the stage's %g s budget for the optimiser (%.1f s spent, about %.1f s for the steps after)",
        plan.optimizer_s,
        run.budget.seconds,
        run.timer.elapsed(),
        run.reserve,
    )


def _optimize_timed(run: _Run, seed, targets, cam_from_world, cameras, split, opt, scale, score, priors):
    """:func:`optimize` until ``run.optimizer_deadline()``, its time in ``run.timer`` as ``optimize`` (the
    held-out curve's points scored meanwhile apart: they are ``heldout_curve``)."""
    every = 0 if score is None else run.curve_every
    start, cpu, before = time.perf_counter(), cpu_seconds(), run.curve_timer.freeze()
    result = optimize(
        seed,
        targets,
        cam_from_world,
        np.stack([c.K for c in cameras]),
        split[0],
        opt,
        scale=scale,
        callback=score,
        callback_every=every,
        pose_views=priors.pose_views if priors.pose_views else None,
        depths=priors.depths,
        deadline=run.optimizer_deadline,
    )
    curve = run.curve_timer.freeze()
    curve_cpu = sum(c for c in curve.cpu if c is not None) - sum(c for c in before.cpu if c is not None)
    wall = time.perf_counter() - start - (curve.total_s - before.total_s)
    run.timer.add("optimize", wall, cpu_seconds() - cpu - curve_cpu)
    return result


def _scorer(run: _Run, heldout, cameras, targets, options: SplatOptions) -> Callable:
    """The held-out curve's callback: mean PSNR and SSIM of plain renders of the held-out views, each view's
    scores kept in ``run.known`` and the seed's renders of the report views in ``run.seed_renders``; timed in
    ``run.curve_timer``, each point's cost measured into ``run.costs``. Points past iteration 0 stop once the
    curve would take more than ``CURVE_SHARE`` of the stage's budget (said in ``run.skipped``)."""
    opt = options.optimize

    def score(iteration: int, seconds: float, g: Gaussians, poses: np.ndarray) -> None:
        point = len(heldout) * (run.costs.render_s + run.costs.score_s)
        if iteration > 0 and run.curve_timer.freeze().total_s + point > CURVE_SHARE * run.budget.seconds:
            run.skipped.setdefault(
                "heldout_curve",
                f"points from iteration {iteration} on left out: {CURVE_SHARE:.0%} "
                f"of the stage's budget ({run.budget.seconds:g} s, --splat-seconds) spent on it",
            )
            return
        with run.curve_timer.stage("heldout_curve"):
            g = g.to(opt.device)
            render_s = score_s = 0.0
            for i in heldout:
                t0 = time.perf_counter()
                view = render_view_on(opt.device, g, poses[i], cameras[i], background=opt.background, raster=opt.raster)
                t1 = time.perf_counter()
                run.known[iteration, i] = image_metrics(view, unit_float(targets[i]))
                render_s, score_s = render_s + t1 - t0, score_s + time.perf_counter() - t1
                if iteration == 0 and len(run.seed_renders) < options.report_views:
                    run.seed_renders[i] = view
            m = np.mean([run.known[iteration, i] for i in heldout], axis=0)
            run.curve.append((iteration, seconds, float(m[0]), float(m[1])))
            run.costs = ViewCosts(render_s / len(heldout), score_s / len(heldout))
            if iteration > 0:
                run.reestimate(len(g))  # moves the optimiser's deadline

    return score


def _probe(g: Gaussians, poses, cameras, view: int, targets, opt: OptimizeOptions) -> ViewCosts:
    """Seconds of one plain render of ``view`` and of scoring it, for the budget's estimates."""
    t0 = time.perf_counter()
    image = render_view_on(opt.device, g, poses[view], cameras[view], background=opt.background, raster=opt.raster)
    t1 = time.perf_counter()
    image_metrics(image, unit_float(targets[view]))
    return ViewCosts(t1 - t0, time.perf_counter() - t1)


def _render_views(g: Gaussians, poses, cameras, views, opt: OptimizeOptions) -> list[torch.Tensor]:
    """Plain renders of ``views`` on the device the splat trained on (``g`` moved there once)."""
    g = g.to(opt.device)
    return [
        render_view_on(opt.device, g, poses[i], cameras[i], background=opt.background, raster=opt.raster) for i in views
    ]


def _heldout_psnr(heldout, poses, cameras, targets, opt, first: float | None = None) -> Callable[[Gaussians], float]:
    """The cleaning's judge: mean PSNR (dB) of plain renders of the held-out views (the figure the report shows).
    ``first``: the judge's first answer when known already (the trained splat's, from the held-out curve)."""
    known = [first]

    def judge(g: Gaussians) -> float:
        if known[0] is not None:
            value, known[0] = known[0], None
            return value
        views = _render_views(g, poses, cameras, heldout, opt)
        return float(np.mean([image_metrics(v, unit_float(targets[i]))[0] for v, i in zip(views, heldout)]))

    return judge


def _pose_check(timer: StageTimer, *args) -> tuple[PoseChange, ...]:
    """:func:`_pose_changes`, timed as the step ``pose_check``."""
    with timer.stage("pose_check"):
        return _pose_changes(*args)


def _pose_changes(
    names, images, cam_from_world, cameras, result: OptimizeResult, split, options: SplatOptions
) -> tuple[PoseChange, ...]:
    """Each refined training frame's correction and how well its render fits its photo afterwards, against
    the median fit of up to 8 training frames kept fixed (all refined: of the refined ones)."""
    train, refined = split[0], list(result.pose_views)
    if not refined:
        return ()
    fixed = [i for i in train if i not in set(refined)]
    fixed = [fixed[k] for k in np.linspace(0, len(fixed) - 1, min(8, len(fixed))).round().astype(int)] if fixed else []
    o = options.optimize
    psnr = {}
    g = result.gaussians.to(o.device)  # moved once, not per view
    for i in dict.fromkeys(refined + fixed):
        pose = result.cam_from_world[i]
        view = render_view_on(o.device, g, pose, cameras[i], background=o.background, raster=o.raster)
        view = apply_color_transform(view, torch.from_numpy(result.color_transforms[i]).float())
        psnr[i] = image_metrics(view, torch.from_numpy(np.ascontiguousarray(images[i])).float() / 255.0)[0]
    reference = float(np.median([psnr[i] for i in (fixed or refined)]))
    scale = scene_scale(np.asarray(cam_from_world)[train], camera_centers(np.asarray(cam_from_world)[train]))
    changes = []
    for i in refined:
        before, after = np.asarray(cam_from_world[i]), result.cam_from_world[i]
        angle = rotation_angle_deg(after[:, :3] @ before[:, :3].T)
        moved = float(np.linalg.norm(camera_centers(after[None])[0] - camera_centers(before[None])[0])) / scale
        flagged = psnr[i] < reference - options.flag_psnr_drop_db
        changes.append(PoseChange(names[i], float(angle), moved, float(psnr[i]), bool(flagged)))
        if flagged:
            logger.warning(
                "splat: %s still fits its photo poorly after pose refinement (PSNR %.1f dB, others %.1f dB): "
                "its camera may be wrong beyond what the splat can correct",
                names[i],
                psnr[i],
                reference,
            )
    return tuple(changes)


def _validate_views(images, names, cam_from_world, cameras, seed=None) -> None:
    """Raise :class:`InputError` unless there is one name, pose and camera per image (and, given ``seed``
    ``(xyz, rgb)``, a finite seed cloud with one colour per point)."""
    if seed is not None:
        _validate_seed(*seed)
    n = len(images)
    if not (len(names) == n == len(cameras) == len(cam_from_world)):
        raise InputError(
            f"run_splat: {n} images, {len(names)} names, {len(cameras)} cameras, {len(cam_from_world)} poses",
            "pass one of each per frame",
        )
    check_shape("cam_from_world", np.asarray(cam_from_world), (n, 3, 4))
    intrinsics = np.array([[c.fx, c.fy, c.cx, c.cy] for c in cameras])
    require_finite("splat", cam_from_world=cam_from_world, intrinsics=intrinsics, fix=CAMERAS_FIX)
    for name, image, cam in zip(names, images, cameras):
        check_shape(f"image {name}", image, (cam.height, cam.width, image.shape[-1] if image.ndim == 3 else 3))
        if image.shape[-1] not in (3, 4):
            raise InputError(f"image {name} has {image.shape[-1]} channels", "pass RGB images (and masks apart)")


CAMERAS_FIX = (
    "the cameras and seed points come from the earlier stages: see which made them in the run's report "
    "(a model: check it with `ffrecon inspect-model` and re-export it; COLMAP: pass --no-colmap or other photos)"
)


def _validate_seed(seed_xyz, seed_rgb) -> None:
    check_shape("seed_xyz", np.asarray(seed_xyz), (None, 3))
    check_shape("seed_rgb", np.asarray(seed_rgb), (len(seed_xyz), 3))
    require_finite("splat", seed_xyz=seed_xyz, seed_rgb=seed_rgb, fix=CAMERAS_FIX)


def _initial_splat(seed_xyz: np.ndarray, seed_rgb: np.ndarray, options: SplatOptions) -> tuple[Gaussians, np.ndarray]:
    """The seed cloud reduced to ``min(max_seed_points, optimize.max_gaussians)`` points, as 3DGS
    Gaussians, and those points (``[M, 3]`` float64)."""
    o = options.optimize
    xyz, rgb = reduce_points(
        np.asarray(seed_xyz, np.float64),
        np.asarray(seed_rgb, np.float32),
        voxel_size=None,
        max_points=min(options.max_seed_points, o.max_gaussians),
        seed=o.seed,
    )
    return initial_gaussians(xyz, rgb, sh_degree=o.sh_degree), xyz


def _evaluate_heldout(
    heldout: Sequence[int],
    names: Sequence[str],
    images: Sequence[np.ndarray],
    poses: np.ndarray,
    cameras: Sequence[PinholeCamera],
    splats: dict[str, Gaussians],
    options: SplatOptions,
    out_dir: Path,
    *,
    known: tuple[dict, dict] = ({}, {}),
) -> tuple[tuple[ViewMetrics, ...], tuple[tuple[str, Path, Path, Path], ...]]:
    """Metrics of the ``seed``, ``optimized`` and ``cleaned`` splats on each held-out view (and of the
    ``cleaned`` one after :func:`color_corrected`), and ``renders/<stem>_{truth,seed,splat}.png`` (plain
    renders) for the first ``report_views`` of them. ``known``: ``({(splat, view): (psnr, ssim)}, {view: seed
    render})`` already measured (by the held-out curve), not rendered again."""
    renders_dir = out_dir / "renders"
    renders_dir.mkdir(parents=True, exist_ok=True)
    o = options.optimize
    scores, seed_renders = known
    splats = {key: g.to(o.device) for key, g in splats.items()}  # moved once, not per view
    metrics, render_paths = [], []
    for j, i in enumerate(heldout):
        truth = torch.from_numpy(np.ascontiguousarray(images[i])).float() / 255.0
        report = j < options.report_views
        views = {
            key: seed_renders[i]
            if key == "seed" and i in seed_renders
            else render_view_on(o.device, g, poses[i], cameras[i], background=o.background, raster=o.raster)
            for key, g in splats.items()
            if (key, i) not in scores or (key == "seed" and report)
        }
        m = {key: scores.get((key, i)) or image_metrics(views[key], truth) for key in splats}
        corrected = image_metrics(color_corrected(views["cleaned"], truth), truth)
        metrics.append(ViewMetrics(names[i], *m["seed"], *m["optimized"], *m["cleaned"], *corrected))
        if report:
            stem = Path(names[i]).stem
            paths = tuple(
                _write_png(renders_dir / f"{stem}_{kind}.png", img)
                for kind, img in (("truth", images[i][..., :3]), ("seed", views["seed"]), ("splat", views["cleaned"]))
            )
            render_paths.append((names[i], *paths))
    return tuple(metrics), tuple(render_paths)


def _write_png(path: Path, rgb: torch.Tensor | np.ndarray) -> Path:
    arr = rgb if isinstance(rgb, np.ndarray) else (rgb.numpy() * 255 + 0.5).astype(np.uint8)
    cv2.imwrite(str(path), cv2.cvtColor(arr, cv2.COLOR_RGB2BGR))
    return path


def _write_outputs(
    out_dir: Path,
    cleaned: Gaussians,
    poses: np.ndarray,
    camera: PinholeCamera,
    options: SplatOptions,
    run: _Run,
) -> tuple[Path, Path | None, dict[str, Path | None]]:
    """``splat.ply``, (when ``options.video`` and the stage's budget allow) ``flythrough.mp4`` and the web
    formats asked for (``{"spz_path": ..., "sog_path": ...}``, see :mod:`ffrecon.formats.web`; splat.spz when
    the budget allows, splat.sog, opt-in, whatever it takes); adds their times to ``run.timer``."""
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


def _video_frames(run: _Run, options: SplatOptions) -> int:
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


def _log_summary(res: SplatResult) -> SplatResult:
    if res.heldout_metrics:
        logger.info(
            "splat: held-out PSNR %.2f -> %.2f dB (cleaned %.2f, colour-corrected %.2f), SSIM %.3f -> %.3f; "
            "%d iterations (%.2f it/s, stopped by %s)",
            res.mean("psnr_seed"),
            res.mean("psnr_optimized"),
            res.mean("psnr_cleaned"),
            res.mean("psnr_cleaned_color_corrected"),
            res.mean("ssim_seed"),
            res.mean("ssim_optimized"),
            res.iterations,
            res.iterations_per_second,
            res.stop_reason,
        )
    return res
