"""Cleaning a splat before export: crop box, low opacity, far away, isolated floaters.

The automatic crop box is where the cameras look and the Gaussians are dense: the robust
(percentile) bounds of the reasonably opaque Gaussians that project into at least one camera,
widened by a margin. Floaters are Gaussians whose mean distance to their nearest neighbours is far
above the typical one (open3d's statistical outlier test).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import open3d as o3d
import torch

from ffrecon.checks import check_number
from ffrecon.errors import InputError
from ffrecon.splat.gaussians import Gaussians
from ffrecon.types import PinholeCamera

logger = logging.getLogger("ffrecon.splat")


@dataclass(frozen=True, kw_only=True)
class CleanOptions:
    crop_box: tuple[tuple[float, float, float], tuple[float, float, float]] | None = (
        None  # (lo, hi) world; None = automatic
    )
    box_percentile: float = 0.5  # automatic box: per-axis percentiles [p, 100 - p] of the seen Gaussians
    box_margin: float = 0.1  # automatic box: widen each side by this fraction of its size
    min_opacity: float = 0.02  # prune Gaussians less opaque than this
    far_factor: float = 4.0  # prune centres further from the median than far_factor x the 95th-percentile distance
    floater_neighbours: int = 16
    floater_std_ratio: float = 4.0  # statistical outlier threshold (in standard deviations); 0 disables
    max_scale_fraction: float = 0.25  # prune Gaussians larger than this fraction of the box diagonal

    def __post_init__(self) -> None:
        if self.crop_box is not None:
            box = np.asarray(self.crop_box, dtype=np.float64)
            if box.shape != (2, 3) or not np.isfinite(box).all() or not (box[0] < box[1]).all():
                raise InputError(
                    f"CleanOptions.crop_box {self.crop_box} is not a box",
                    "set crop_box to ((x0, y0, z0), (x1, y1, z1)) with finite x0 < x1, y0 < y1, z0 < z1, "
                    "or None for the automatic box",
                )
        check_number("CleanOptions.box_percentile", self.box_percentile, low=0, high=50)
        check_number("CleanOptions.min_opacity", self.min_opacity, low=0, high=1)
        for name in ("box_margin", "floater_std_ratio"):  # floater_std_ratio 0: no floater pruning
            check_number(f"CleanOptions.{name}", getattr(self, name), low=0)
        for name in ("far_factor", "max_scale_fraction"):
            check_number(f"CleanOptions.{name}", getattr(self, name), low=0, low_open=True)
        check_number("CleanOptions.floater_neighbours", self.floater_neighbours, low=1, integer=True)


@dataclass(frozen=True)
class CleanReport:
    count_before: int
    count_after: int
    removed: dict[str, int]  # reason -> count (each Gaussian counted under the first reason that hits it)
    crop_box: tuple[tuple[float, ...], tuple[float, ...]]
    automatic_box: bool

    def to_dict(self) -> dict:
        return {
            "count_before": self.count_before,
            "count_after": self.count_after,
            "removed": dict(self.removed),
            "crop_box": {"lo": list(self.crop_box[0]), "hi": list(self.crop_box[1]), "automatic": self.automatic_box},
        }


def seen_by_cameras(points: np.ndarray, cam_from_world: np.ndarray, cameras: Sequence[PinholeCamera]) -> np.ndarray:
    """``[M]`` bool: the point projects inside at least one image, in front of its camera."""
    seen = np.zeros(len(points), bool)
    for pose, cam in zip(cam_from_world, cameras):
        pc = points @ pose[:3, :3].T + pose[:3, 3]
        z = pc[:, 2]
        front = z > 1e-6
        u = cam.fx * pc[:, 0] / np.where(front, z, 1.0) + cam.cx
        v = cam.fy * pc[:, 1] / np.where(front, z, 1.0) + cam.cy
        seen |= front & (u >= 0) & (u <= cam.width) & (v >= 0) & (v <= cam.height)
    return seen


def auto_crop_box(
    points: np.ndarray,
    opacity: np.ndarray,
    cam_from_world: np.ndarray,
    cameras: Sequence[PinholeCamera],
    *,
    percentile: float = 0.5,
    margin: float = 0.1,
) -> tuple[np.ndarray, np.ndarray]:
    """``(lo [3], hi [3])``: robust bounds of the seen, reasonably opaque points plus a margin."""
    seen = seen_by_cameras(points, cam_from_world, cameras)
    pick = seen & (opacity >= 0.1)
    if pick.sum() < 10:
        pick = seen if seen.sum() >= 10 else np.ones(len(points), bool)
    lo, hi = np.percentile(points[pick], [percentile, 100 - percentile], axis=0)
    pad = margin * (hi - lo)
    return lo - pad, hi + pad


def floater_mask(points: np.ndarray, neighbours: int, std_ratio: float) -> np.ndarray:
    """``[M]`` bool, True for statistical outliers (isolated points)."""
    if std_ratio <= 0 or len(points) <= neighbours:
        return np.zeros(len(points), bool)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    _, kept = pcd.remove_statistical_outlier(nb_neighbors=neighbours, std_ratio=std_ratio)
    out = np.ones(len(points), bool)
    out[np.asarray(kept, dtype=np.int64)] = False
    return out


def clean_gaussians(
    gaussians: Gaussians,
    cam_from_world: np.ndarray,
    cameras: Sequence[PinholeCamera],
    options: CleanOptions = CleanOptions(),
) -> tuple[Gaussians, CleanReport]:
    """Remove Gaussians outside the crop box, too transparent, too large, far away or isolated.

    Args:
        gaussians: the optimised splat (world frame).
        cam_from_world: ``[N, 3, 4]`` the cameras the splat was fitted to; cameras: their intrinsics.
    Returns:
        ``(cleaned Gaussians, CleanReport)``.
    """
    means = gaussians.means.detach().double().numpy()
    opacity = torch.sigmoid(gaussians.opacity_logits.detach()).double().numpy()
    scale = torch.exp(gaussians.log_scales.detach()).amax(1).double().numpy()
    if options.crop_box is None:
        lo, hi = auto_crop_box(
            means, opacity, cam_from_world, cameras, percentile=options.box_percentile, margin=options.box_margin
        )
    else:
        lo, hi = (np.asarray(v, np.float64) for v in options.crop_box)
    keep = np.ones(len(means), bool)
    removed: dict[str, int] = {}

    def drop(reason: str, bad: np.ndarray) -> None:
        hit = keep & bad
        removed[reason] = int(hit.sum())
        keep[hit] = False

    drop("outside_crop_box", ~np.all((means >= lo) & (means <= hi), axis=1))
    drop("low_opacity", opacity < options.min_opacity)
    drop("too_large", scale > options.max_scale_fraction * float(np.linalg.norm(hi - lo)))
    if keep.sum() > 10:
        center = np.median(means[keep], axis=0)
        dist = np.linalg.norm(means - center, axis=1)
        drop("far_away", dist > options.far_factor * np.percentile(dist[keep], 95))
    if keep.sum() > options.floater_neighbours:
        idx = np.flatnonzero(keep)
        bad = np.zeros(len(means), bool)
        bad[idx] = floater_mask(means[idx], options.floater_neighbours, options.floater_std_ratio)
        drop("isolated_floater", bad)
    out = gaussians.subset(torch.from_numpy(keep))
    report = CleanReport(
        len(means), len(out), removed, (tuple(map(float, lo)), tuple(map(float, hi))), options.crop_box is None
    )
    logger.info(
        "clean: %d -> %d Gaussians (%s)", len(means), len(out), ", ".join(f"{k} {v}" for k, v in removed.items())
    )
    return out, report
