"""The splat stage's evaluation: render a view and score it against its photo (:func:`render_and_score`, the one
place that does), for the held-out curve, the cleaning's judge, the pose check and the final held-out scores.

The held-out views (every ``holdout_every``-th frame, starting with the first) are chosen once, by
:func:`split_views`: they are never trained on nor seeded from, and PSNR and SSIM are measured on them for the
seed, the optimised and the cleaned (exported) splat. The cleaned splat is also scored after a colour correction,
as is usual for photos whose exposure and white balance vary: an affine colour transform from its render to the
held-out photo, fitted by least squares on that photo (see :func:`ffrecon.splat.appearance.fit_color_transform`),
so that a held-out frame's own exposure, which no training image shows, does not count as an error.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ffrecon.gaussians import Gaussians
from ffrecon.geometry.poses import camera_centers
from ffrecon.geometry.rotations import rotation_angle_deg
from ffrecon.splat.appearance import apply_color_transform, fit_color_transform
from ffrecon.splat.budget import ViewCosts
from ffrecon.splat.optimize import scene_scale
from ffrecon.splat.optimize_options import OptimizeOptions, OptimizeResult
from ffrecon.splat.options import SplatOptions
from ffrecon.splat.outputs import write_png
from ffrecon.splat.render_gsplat import render_view_on
from ffrecon.splat.result import PoseChange, ViewMetrics
from ffrecon.splat.ssim import ssim_mean
from ffrecon.splat.stage_run import StageRun
from ffrecon.splat.train_views import unit_float
from ffrecon.types import PinholeCamera

logger = logging.getLogger("ffrecon.splat")


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


@dataclass(frozen=True)
class Scored:
    """A render of one view and its scores against the view's photo, with the seconds each took (the budget's
    estimates read them)."""

    image: torch.Tensor  # [H, W, 3] float32 in [0, 1], on the device it was rendered on
    psnr: float  # dB
    ssim: float
    render_s: float
    score_s: float

    @property
    def scores(self) -> tuple[float, float]:
        return self.psnr, self.ssim


def render_view(g: Gaussians, pose: np.ndarray, camera: PinholeCamera, opt: OptimizeOptions) -> torch.Tensor:
    """A plain render of one view on ``opt.device`` (``g`` already there: move it once, not per view), with the
    optimisation's background and rasteriser. ``pose``: ``[3, 4]`` cam_from_world."""
    return render_view_on(opt.device, g, pose, camera, background=opt.background, raster=opt.raster)


def render_and_score(
    g: Gaussians,
    pose: np.ndarray,
    camera: PinholeCamera,
    photo: torch.Tensor,
    opt: OptimizeOptions,
    *,
    color_transform: torch.Tensor | None = None,
) -> Scored:
    """Render one view (:func:`render_view`) and score it against ``photo`` (:func:`image_metrics`; ``[H, W, 3]`` or
    ``[H, W, 4]`` with a mask, uint8 or float in [0, 1]): the one place the stage renders and scores, for the
    held-out curve, the cleaning's judge, the budget's probe, the pose check and the final held-out scores.
    ``color_transform``: ``[3, 4]`` ``[A | b]`` applied to the render before it is scored (a training view's
    learnt exposure)."""
    t0 = time.perf_counter()
    image = render_view(g, pose, camera, opt)
    if color_transform is not None:
        image = apply_color_transform(image, color_transform)
    t1 = time.perf_counter()
    psnr, ssim = image_metrics(image, unit_float(photo))
    return Scored(image, psnr, ssim, t1 - t0, time.perf_counter() - t1)


CURVE_SHARE = 0.15  # the held-out curve's points stop once they would take more of the stage's budget than this


def known_scores(run: StageRun, heldout, iterations: int) -> dict[tuple[str, int], tuple[float, float]]:
    """The held-out scores of the seed and of the optimised splat the curve already measured."""
    known = {("seed", i): run.known[0, i] for i in heldout if (0, i) in run.known}
    return known | {("optimized", i): run.known[iterations, i] for i in heldout if (iterations, i) in run.known}


def heldout_curve_scorer(run: StageRun, heldout, cameras, targets, options: SplatOptions) -> Callable:
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
                scored = render_and_score(g, poses[i], cameras[i], targets[i], opt)
                run.known[iteration, i] = scored.scores
                render_s, score_s = render_s + scored.render_s, score_s + scored.score_s
                if iteration == 0 and len(run.seed_renders) < options.report_views:
                    run.seed_renders[i] = scored.image
            m = np.mean([run.known[iteration, i] for i in heldout], axis=0)
            run.curve.append((iteration, seconds, float(m[0]), float(m[1])))
            run.costs = ViewCosts(render_s / len(heldout), score_s / len(heldout))
            if iteration > 0:
                run.reestimate(len(g))  # moves the optimiser's deadline

    return score


def probe_costs(g: Gaussians, poses, cameras, view: int, targets, opt: OptimizeOptions) -> ViewCosts:
    """Seconds of one plain render of ``view`` and of scoring it, for the budget's estimates."""
    scored = render_and_score(g, poses[view], cameras[view], targets[view], opt)
    return ViewCosts(scored.render_s, scored.score_s)


def heldout_psnr_judge(
    heldout, poses, cameras, targets, opt, first: float | None = None
) -> Callable[[Gaussians], float]:
    """The cleaning's judge: mean PSNR (dB) of plain renders of the held-out views (the figure the report shows).
    ``first``: the judge's first answer when known already (the trained splat's, from the held-out curve)."""
    known = [first]

    def judge(g: Gaussians) -> float:
        if known[0] is not None:
            value, known[0] = known[0], None
            return value
        g = g.to(opt.device)
        return float(np.mean([render_and_score(g, poses[i], cameras[i], targets[i], opt).psnr for i in heldout]))

    return judge


def pose_changes(
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
        transform = torch.from_numpy(result.color_transforms[i]).float()
        photo = torch.from_numpy(np.ascontiguousarray(images[i]))
        psnr[i] = render_and_score(g, result.cam_from_world[i], cameras[i], photo, o, color_transform=transform).psnr
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


def _heldout_view(i: int, photo, pose, camera, splats: dict[str, Gaussians], o: OptimizeOptions, known, report: bool):
    """``(renders, scores)`` of held-out view ``i``, each by splat (``seed``, ``optimized``, ``cleaned``): the scores
    ``known`` already (see :func:`evaluate_heldout`) taken as they are, the others rendered and scored; the seed's
    render kept (or made) for a ``report`` view."""
    scores, seed_renders = known
    views, m = {}, {}
    for key, g in splats.items():
        if (key, i) in scores:
            m[key] = scores[key, i]
            if key == "seed" and report:
                views[key] = seed_renders[i] if i in seed_renders else render_view(g, pose, camera, o)
        else:
            scored = render_and_score(g, pose, camera, photo, o)
            views[key], m[key] = scored.image, scored.scores
    return views, m


def evaluate_heldout(
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
    splats = {key: g.to(o.device) for key, g in splats.items()}  # moved once, not per view
    metrics, render_paths = [], []
    for j, i in enumerate(heldout):
        photo = torch.from_numpy(np.ascontiguousarray(images[i]))
        truth = unit_float(photo)
        report = j < options.report_views
        views, m = _heldout_view(i, photo, poses[i], cameras[i], splats, o, known, report)
        corrected = image_metrics(color_corrected(views["cleaned"], truth), truth)
        metrics.append(ViewMetrics(names[i], *m["seed"], *m["optimized"], *m["cleaned"], *corrected))
        if report:
            stem = Path(names[i]).stem
            paths = tuple(
                write_png(renders_dir / f"{stem}_{kind}.png", img)
                for kind, img in (("truth", images[i][..., :3]), ("seed", views["seed"]), ("splat", views["cleaned"]))
            )
            render_paths.append((names[i], *paths))
    return tuple(metrics), tuple(render_paths)
