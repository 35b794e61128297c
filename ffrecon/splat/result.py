"""What the splat stage returns: :class:`SplatResult`, with its held-out scores and pose corrections."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np

from ffrecon.splat.clean import CleanReport
from ffrecon.timing import Timings


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
