"""Cleaning a splat before export: crop box, low opacity, far away, isolated floaters.

The automatic crop box is where the cameras look and the Gaussians are dense: the robust
(percentile) bounds of the reasonably opaque Gaussians that project into at least one camera,
widened by a margin. Floaters are Gaussians whose mean distance to their nearest neighbours is far
above the typical one (open3d's statistical outlier test).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ffrecon.checks import check_number
from ffrecon.errors import InputError
from ffrecon.types import PinholeCamera

if TYPE_CHECKING:
    from ffrecon.gaussians import Gaussians

logger = logging.getLogger("ffrecon.splat")

# A crop box is axis-aligned in the world of the run's final cameras: sparse/0's, which transforms.json
# (applied_transform identity), points.ply and splat.ply share. Its file (docs/camera_paths.md) says so.
CROP_BOX_FRAME = "sparse/0"
CropBox = tuple[tuple[float, float, float], tuple[float, float, float]]
_BOX_FIX = "give x0 < x1, y0 < y1, z0 < z1, finite"


@dataclass(frozen=True, kw_only=True)
class CleanOptions:
    crop_box: CropBox | None = None  # (lo, hi) in the final cameras' world (CROP_BOX_FRAME); None = automatic
    box_percentile: float = 0.5  # automatic box: per-axis percentiles [p, 100 - p] of the seen Gaussians
    box_margin: float = 0.1  # automatic box: widen each side by this fraction of its size
    min_opacity: float = 0.02  # prune Gaussians less opaque than this
    far_factor: float = 4.0  # prune centres further from the median than far_factor x the 95th-percentile distance
    floater_neighbours: int = 16
    floater_std_ratio: float = 4.0  # statistical outlier threshold (in standard deviations); 0 disables
    max_scale_fraction: float = 0.25  # prune Gaussians larger than this fraction of the box diagonal
    # With held-out views to judge by: a step is kept only while their mean PSNR stays within this (dB) of
    # the trained splat's, all steps together. A crop box the user gave is always applied (its cost reported).
    max_psnr_drop_db: float = 0.1

    def __post_init__(self) -> None:
        if self.crop_box is not None:
            fix = "set crop_box to ((x0, y0, z0), (x1, y1, z1)) with finite x0 < x1, y0 < y1, z0 < z1, or None"
            try:
                lo, hi = self.crop_box
            except (TypeError, ValueError):
                raise InputError(f"CleanOptions.crop_box {self.crop_box!r} is not two corners", fix) from None
            object.__setattr__(self, "crop_box", check_crop_box(lo, hi, "CleanOptions.crop_box", fix))
        check_number("CleanOptions.box_percentile", self.box_percentile, low=0, high=50)
        check_number("CleanOptions.min_opacity", self.min_opacity, low=0, high=1)
        for name in ("box_margin", "floater_std_ratio", "max_psnr_drop_db"):  # floater_std_ratio 0: no floater pruning
            check_number(f"CleanOptions.{name}", getattr(self, name), low=0)
        for name in ("far_factor", "max_scale_fraction"):
            check_number(f"CleanOptions.{name}", getattr(self, name), low=0, low_open=True)
        check_number("CleanOptions.floater_neighbours", self.floater_neighbours, low=1, integer=True)


def check_crop_box(lo, hi, where: str, fix: str) -> CropBox:
    """``((x0, y0, z0), (x1, y1, z1))`` as floats, or an :class:`InputError` (``where`` names the box, ``fix``
    says how to give a good one) when ``lo``/``hi`` are not 3 finite numbers each with ``lo < hi``.

    >>> check_crop_box([0, 0, 0], [1, 2, 3], "box", "")
    ((0.0, 0.0, 0.0), (1.0, 2.0, 3.0))
    """
    try:
        box = np.asarray([lo, hi], dtype=np.float64)
    except (TypeError, ValueError):
        box = None
    if box is None or box.shape != (2, 3):
        raise InputError(f"{where} is not two corners of 3 numbers each (got {lo!r} and {hi!r})", fix)
    if not np.isfinite(box).all():
        raise InputError(f"{where} has a value that is not a finite number: {box.tolist()}", fix)
    axes = [name for name, a, b in zip("xyz", box[0], box[1]) if not a < b]
    if axes:
        raise InputError(f"{where} is empty along {', '.join(axes)}: lo {box[0].tolist()}, hi {box[1].tolist()}", fix)
    return tuple(map(float, box[0])), tuple(map(float, box[1]))


def read_crop_box(file: Path) -> CropBox:
    """The box of a crop-box file ``{"frame": "sparse/0", "lo": [x0, y0, z0], "hi": [x1, y1, z1]}`` (what
    :func:`write_crop_box` and ``ffrecon view`` write); every problem an :class:`InputError`."""
    file = Path(file)
    fix = f'write it as {{"frame": "{CROP_BOX_FRAME}", "lo": [x0, y0, z0], "hi": [x1, y1, z1]}} with x0 < x1 ...'
    if not file.is_file():
        raise InputError(f"crop box file {file} does not exist", "pass six numbers x0 y0 z0 x1 y1 z1, or a box file")
    try:
        data = json.loads(file.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise InputError(f"crop box file {file} is not JSON ({err})", fix) from None
    if not isinstance(data, dict) or "lo" not in data or "hi" not in data:
        raise InputError(f"crop box file {file} has no lo and hi", fix)
    if data.get("frame", CROP_BOX_FRAME) != CROP_BOX_FRAME:
        raise InputError(f"crop box file {file} is in frame {data['frame']!r}, not {CROP_BOX_FRAME!r}", fix)
    return check_crop_box(data["lo"], data["hi"], f"crop box file {file}", fix)


def write_crop_box(file: Path, box: CropBox) -> Path:
    """Write ``box`` as a crop-box file (see :func:`read_crop_box`); returns ``file``."""
    lo, hi = check_crop_box(box[0], box[1], "the crop box", _BOX_FIX)
    Path(file).write_text(json.dumps({"frame": CROP_BOX_FRAME, "lo": list(lo), "hi": list(hi)}, indent=1) + "\n")
    return Path(file)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def crop_box_from_args(values: Sequence[str], flag: str = "--crop-box") -> CropBox:
    """The box of a command line's ``values``: six numbers ``x0 y0 z0 x1 y1 z1``, or one crop-box file."""
    fix = f"pass {flag} x0 y0 z0 x1 y1 z1 (x0 < x1, y0 < y1, z0 < z1) or {flag} BOX.json"
    if len(values) == 1 and not Path(values[0]).exists() and _is_number(values[0]):
        fix += " (argparse takes -2.5 as a number, -2.5e0 as an option: write negative numbers without exponents)"
    elif len(values) == 1:
        return read_crop_box(Path(values[0]))
    if len(values) != 6:
        raise InputError(
            f"{flag} takes 6 numbers or 1 file, not {len(values)} value{'' if len(values) == 1 else 's'}", fix
        )
    try:
        numbers = [float(v) for v in values]
    except ValueError:
        raise InputError(f"{flag} {' '.join(values)} is not six numbers", fix) from None
    return check_crop_box(numbers[:3], numbers[3:], f"{flag} {' '.join(values)}", fix)


@dataclass(frozen=True)
class CleanStep:
    """One cleaning step: what it would remove and, when judged, the held-out PSNR without and with it."""

    name: str  # outside_crop_box, low_opacity, too_large, far_away, isolated_floater
    candidates: int  # Gaussians it hits among those still kept
    applied: bool
    psnr_before: float | None = None  # mean held-out PSNR (dB) before the step; None: not judged
    psnr_after: float | None = None  # ... with the step applied
    reason: str = ""  # why it was applied or skipped

    def to_dict(self) -> dict:
        out = {"step": self.name, "candidates": self.candidates, "applied": self.applied, "reason": self.reason}
        if self.psnr_before is not None:
            out.update(psnr_before=self.psnr_before, psnr_after=self.psnr_after)
        return out


@dataclass(frozen=True)
class CleanReport:
    count_before: int
    count_after: int
    removed: dict[str, int]  # reason -> count removed (each Gaussian counted under the first step that took it)
    crop_box: tuple[tuple[float, ...], tuple[float, ...]]
    automatic_box: bool
    steps: tuple[CleanStep, ...] = ()

    def to_dict(self) -> dict:
        return {
            "count_before": self.count_before,
            "count_after": self.count_after,
            "removed": dict(self.removed),
            "crop_box": {
                "frame": CROP_BOX_FRAME,
                "lo": list(self.crop_box[0]),
                "hi": list(self.crop_box[1]),
                "automatic": self.automatic_box,
            },
            "steps": [step.to_dict() for step in self.steps],
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
    import open3d as o3d  # 0.45 s: here, so that loading CleanOptions (every run) does not load it

    if std_ratio <= 0 or len(points) <= neighbours:
        return np.zeros(len(points), bool)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    _, kept = pcd.remove_statistical_outlier(nb_neighbors=neighbours, std_ratio=std_ratio)
    out = np.ones(len(points), bool)
    out[np.asarray(kept, dtype=np.int64)] = False
    return out


class _Steps:
    """The cleaning's steps in order over one keep mask, each judged on the held-out views when a judge is given."""

    def __init__(self, gaussians: Gaussians, judge: Callable[[Gaussians], float] | None, max_drop_db: float):
        self.gaussians, self.judge, self.max_drop_db = gaussians, judge, max_drop_db
        self.keep = np.ones(len(gaussians.means), bool)
        self.steps: list[CleanStep] = []
        self.current = judge(gaussians) if judge is not None else None  # held-out PSNR of the splat as it stands
        # Steps together may cost at most max_drop_db below the trained splat (a given crop box may cost more).
        self.floor = self.current - max_drop_db if judge is not None else None

    def step(self, name: str, bad: np.ndarray, forced: bool = False) -> None:
        import torch  # 0.9 s: here, so that loading CleanOptions (every run) does not load it

        hit = self.keep & bad
        if not hit.any():
            self.steps.append(CleanStep(name, 0, False, self.current, self.current, "nothing to remove"))
            return
        if self.judge is None:
            self.keep[hit] = False
            self.steps.append(CleanStep(name, int(hit.sum()), True, reason="applied (no held-out views to judge by)"))
            return
        after = self.judge(self.gaussians.subset(torch.from_numpy(self.keep & ~hit)))
        ok = forced or after >= self.floor
        why = "the crop box you gave" if forced else ("kept" if ok else "skipped")
        why += f": held-out PSNR {after - self.current:+.2f} dB"
        self.steps.append(CleanStep(name, int(hit.sum()), ok, self.current, after, why))
        if ok:
            self.keep[hit] = False
            self.current = after
            self.floor = min(self.floor, after)


def clean_gaussians(
    gaussians: Gaussians,
    cam_from_world: np.ndarray,
    cameras: Sequence[PinholeCamera],
    options: CleanOptions = CleanOptions(),
    *,
    judge: Callable[[Gaussians], float] | None = None,
) -> tuple[Gaussians, CleanReport]:
    """Remove Gaussians outside the crop box, too transparent, too large, far away or isolated.

    Args:
        gaussians: the optimised splat (world frame).
        cam_from_world: ``[N, 3, 4]`` the cameras the splat was fitted to; cameras: their intrinsics.
        judge: the mean held-out PSNR (dB) of a splat. Given, each step is tried in turn and kept only if
            the splat stays within ``options.max_psnr_drop_db`` of the trained one's (all kept steps
            together; an explicit crop box is always kept, and what it costs is not counted): the
            background of a forward-facing or unbounded capture is large, far and faint, which is what
            the thresholds target. None: every step is applied.
    Returns:
        ``(cleaned Gaussians, CleanReport)``.
    """
    import torch  # 0.9 s: here, so that loading CleanOptions (every run) does not load it

    means = gaussians.means.detach().double().numpy()
    opacity = torch.sigmoid(gaussians.opacity_logits.detach()).double().numpy()
    scale = torch.exp(gaussians.log_scales.detach()).amax(1).double().numpy()
    if options.crop_box is None:
        lo, hi = auto_crop_box(
            means, opacity, cam_from_world, cameras, percentile=options.box_percentile, margin=options.box_margin
        )
    else:
        lo, hi = (np.asarray(v, np.float64) for v in options.crop_box)
    run = _Steps(gaussians, judge, options.max_psnr_drop_db)
    keep, step = run.keep, run.step
    step("outside_crop_box", ~np.all((means >= lo) & (means <= hi), axis=1), forced=options.crop_box is not None)
    step("low_opacity", opacity < options.min_opacity)
    step("too_large", scale > options.max_scale_fraction * float(np.linalg.norm(hi - lo)))
    if keep.sum() > 10:
        center = np.median(means[keep], axis=0)
        dist = np.linalg.norm(means - center, axis=1)
        step("far_away", dist > options.far_factor * np.percentile(dist[keep], 95))
    if keep.sum() > options.floater_neighbours:
        idx = np.flatnonzero(keep)
        bad = np.zeros(len(means), bool)
        bad[idx] = floater_mask(means[idx], options.floater_neighbours, options.floater_std_ratio)
        step("isolated_floater", bad)
    out = gaussians.subset(torch.from_numpy(keep))
    steps = run.steps
    removed = {s.name: s.candidates if s.applied else 0 for s in steps}
    report = CleanReport(
        len(means),
        len(out),
        removed,
        (tuple(map(float, lo)), tuple(map(float, hi))),
        options.crop_box is None,
        tuple(steps),
    )
    logger.info(
        "clean: %d -> %d Gaussians (%s)",
        len(means),
        len(out),
        "; ".join(s.reason and f"{s.name} {s.candidates}, {s.reason}" for s in steps),
    )
    return out, report
