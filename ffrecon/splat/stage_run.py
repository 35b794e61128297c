"""What the splat stage's steps share (:class:`StageRun`: its timer, budget, held-out curve and scores) and how the
stage's budget is split between the optimiser and the steps after it."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from ffrecon.splat.budget import AfterSteps, StageBudget, Step, ViewCosts, after_steps, plan_budget
from ffrecon.splat.optimize import optimize
from ffrecon.splat.options import SplatOptions, ViewPriors
from ffrecon.timing import StageTimer, cpu_seconds

logger = logging.getLogger("ffrecon.splat")


@dataclass
class StageRun:
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


def after_estimates(
    run: StageRun, gaussians: int, split, options: SplatOptions, priors: ViewPriors, *, curve: bool
) -> list:
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


def plan_steps(
    run: StageRun, seed_count: int, split, options: SplatOptions, priors: ViewPriors, *, curve: bool
) -> None:
    """Split what the stage's budget leaves after the steps so far between the optimiser and the estimated
    steps after it (optional ones left out when they would take more than half of it): sets ``run.reserve``,
    ``run.kept``, ``run.estimate`` and ``run.after``. The splat may grow to ``optimize.max_gaussians``: the
    first estimate assumes renders slow down with it (the seed's own render, measured, is slower than a
    trained splat's: its Gaussians are larger); the held-out curve's points measure them again."""
    o = options.optimize
    grown = o.max_gaussians if o.densify is not None else seed_count
    factor = 1.0 + 0.25 * np.log2(max(1.0, grown / max(seed_count, 1)))
    run.estimate = lambda count: after_estimates(run, count, split, options, priors, curve=curve)
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


def optimize_timed(run: StageRun, seed, targets, cam_from_world, cameras, split, opt, scale, score, priors):
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
