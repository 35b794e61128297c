"""The splat's time budget as an upper bound: the whole stage's (``--splat-seconds``), split between the
optimiser and the steps after it (:func:`plan_budget`, :class:`StageBudget`), and each optimiser step's
seconds predicted before it runs (:class:`StepClock`)."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass


class StepClock:
    """Predicts the next step's seconds from its pixels, so that the time budget ends the loop before a step
    would overrun it (one step on a 27 MP view takes 20 s: checking only after it overran a 10 s budget).

    A step costs a part per Gaussian and a part per pixel. The prediction for a view size already seen is
    the last step's time at that size; for a new size, the line through the last times of the smallest
    and the largest sizes seen (slope at least 0), or with one size seen, its time scaled up by the pixels
    (an overestimate: near the end of the budget a step may be left out rather than overrun it). Before
    any step: 0.
    """

    def __init__(self) -> None:
        self.last: dict[int, float] = {}  # pixels -> seconds of the last step at that size

    def predict(self, pixels: int) -> float:
        if pixels in self.last or not self.last:
            return self.last.get(pixels, 0.0)
        small, large = min(self.last), max(self.last)
        if small == large:
            return self.last[small] * max(1.0, pixels / small)
        slope = max(0.0, (self.last[large] - self.last[small]) / (large - small))
        return max(0.0, self.last[small] + slope * (pixels - small))

    def record(self, pixels: int, seconds: float) -> float:
        """Note a step's seconds; returns them."""
        self.last[pixels] = seconds
        return seconds


@dataclass(frozen=True)
class Step:
    """A step of the splat stage after the optimiser, with its estimated seconds; ``optional`` ones may be
    left out (or, the video, shortened) when the stage's budget runs short."""

    name: str
    seconds: float
    optional: bool = True
    value: int = 0  # optional steps are left out lowest value first


@dataclass(frozen=True)
class BudgetPlan:
    """The optimiser's share of the stage's budget and the steps after it that fit."""

    optimizer_s: float  # seconds the optimiser may take (its held-out curve included); 0: one iteration
    kept: tuple[str, ...]  # the steps after it, in order
    skipped: dict[str, str]  # step -> why it was left out


def plan_budget(budget_s: float, spent_s: float, after: Sequence[Step], *, min_share: float = 0.5) -> BudgetPlan:
    """Split what is left of a stage's ``budget_s`` after ``spent_s`` between the optimiser and the ``after``
    steps: the optimiser gets what the steps do not need, and while that is less than ``min_share`` of what
    is left, optional steps are left out, lowest ``value`` first (then the last listed). Required steps are
    always kept, even when they alone overrun the budget (the optimiser then gets 0).

    >>> plan = plan_budget(30.0, 2.0, [Step("evaluate", 2.0, optional=False), Step("video", 20.0)])
    >>> plan.optimizer_s, plan.kept
    (26.0, ('evaluate',))
    >>> plan_budget(30.0, 2.0, [Step("evaluate", 2.0, optional=False), Step("video", 5.0)]).optimizer_s
    21.0
    """
    left = max(0.0, budget_s - spent_s)
    kept = list(after)
    skipped: dict[str, str] = {}
    optional = sorted((s for s in reversed(after) if s.optional), key=lambda s: s.value)
    for step in optional:
        if left - sum(s.seconds for s in kept) >= min_share * left:
            break
        kept.remove(step)
        skipped[step.name] = budget_reason(step.seconds, left, budget_s, "before the optimiser")
    return BudgetPlan(max(0.0, left - sum(s.seconds for s in kept)), tuple(s.name for s in kept), skipped)


def budget_reason(needed_s: float, left_s: float, budget_s: float, when: str) -> str:
    """Why a step was left out, for the report."""
    return (
        f"the splat stage's budget ({budget_s:g} s, --splat-seconds): about {needed_s:.1f} s needed, "
        f"{max(0.0, left_s):.1f} s left {when}"
    )


class StageBudget:
    """The stage's deadline, from when its timer started: ``seconds`` of wall clock in all."""

    def __init__(self, seconds: float, started: float) -> None:
        self.seconds = float(seconds)
        self.deadline = started + self.seconds

    def left(self) -> float:
        return self.deadline - time.perf_counter()

    def skip_reason(self, needed_s: float) -> str | None:
        """None when a step of about ``needed_s`` fits in what is left, else why it is left out."""
        left = self.left()
        return None if needed_s <= left else budget_reason(needed_s, left, self.seconds, "when it was due")


@dataclass(frozen=True)
class ViewCosts:
    """Measured seconds of one full-size render of a view and of scoring it (PSNR and SSIM)."""

    render_s: float
    score_s: float


# Seconds per Gaussian of the steps that do not render, with a margin (measured on the 2-core machine, 60k
# Gaussians: the cleaning less its judge 0.2-0.7 s, splat.ply 0.01-0.03 s, splat.spz 0.04-0.33 s), and of
# encoding a video frame.
CLEAN_S_PER_GAUSSIAN = 8e-6
WRITE_S_PER_GAUSSIAN = 1.5e-6
SPZ_S_PER_GAUSSIAN = 5e-6
VIDEO_ENCODE_S = 0.005
JUDGE_CALLS = 5  # the cleaning's judge: the splat less each of its steps (the splat itself is known)


def after_steps(
    costs: ViewCosts,
    *,
    gaussians: int,
    heldout: int,
    pose_views: int,
    video_frames: int,
    spz: bool,
    curve: bool,
) -> list[Step]:
    """The splat stage's steps after the optimiser in the order they run, with their estimated seconds:
    the held-out curve's last point, the cleaning (its judge apart), the pose check of ``pose_views``
    refined frames (and up to 8 fixed ones), the held-out evaluation (the seed and the optimised splat
    already scored by the curve when ``curve``), splat.ply, splat.spz and the video.

    >>> steps = after_steps(ViewCosts(0.1, 0.05), gaussians=10_000, heldout=2, pose_views=0, video_frames=90,
    ...                     spz=True, curve=True)
    >>> [(s.name, round(s.seconds, 2)) for s in steps]  # doctest: +NORMALIZE_WHITESPACE
    [('heldout_curve', 0.3), ('clean_judge', 1.0), ('clean', 0.08), ('evaluate', 0.4), ('write_ply', 0.02),
     ('write_spz', 0.05), ('video', 9.45)]
    """
    view = costs.render_s + costs.score_s
    steps = []
    if heldout and curve:
        steps.append(Step("heldout_curve", heldout * view, value=4))
    if heldout:
        steps.append(Step("clean_judge", JUDGE_CALLS * heldout * costs.render_s, value=5))
    steps.append(Step("clean", gaussians * CLEAN_S_PER_GAUSSIAN, optional=False))
    if pose_views:
        steps.append(Step("pose_check", (pose_views + 8) * view, optional=False))  # its flags are evidence
    if heldout:  # the cleaned splat rendered and scored twice (plain, colour-corrected); seed and optimised too
        renders = 1 if curve else 3
        steps.append(Step("evaluate", heldout * (renders * costs.render_s + (renders + 1) * costs.score_s), False))
    steps.append(Step("write_ply", gaussians * WRITE_S_PER_GAUSSIAN, optional=False))
    if spz:
        steps.append(Step("write_spz", gaussians * SPZ_S_PER_GAUSSIAN, value=2))
    if video_frames:
        steps.append(Step("video", video_frames * (costs.render_s + VIDEO_ENCODE_S), value=1))
    return steps


class AfterSteps:
    """The steps after the optimiser at work: each optional one runs only if it and the required steps after
    it fit in what is left of the stage's budget (re-estimated as renders are measured); ``skipped`` says
    why the others did not run."""

    def __init__(self, budget: StageBudget, steps: Sequence[Step], skipped: dict[str, str]) -> None:
        self.budget, self.steps, self.skipped = budget, list(steps), skipped  # shared: the stage adds its own

    def update(self, steps: Sequence[Step]) -> None:
        """New estimates (from costs measured since); steps already left out stay out."""
        self.steps = list(steps)

    def needed(self, name: str) -> float:
        """The step's estimate and those of the required steps after it."""
        names = [s.name for s in self.steps]
        if name not in names:
            return 0.0
        i = names.index(name)
        return self.steps[i].seconds + sum(s.seconds for s in self.steps[i + 1 :] if not s.optional)

    def reserve(self, name: str) -> float:
        """Seconds the required steps after ``name`` need."""
        return self.needed(name) - next((s.seconds for s in self.steps if s.name == name), 0.0)

    def allowed(self, name: str) -> bool:
        """Whether optional step ``name`` runs now (noted in ``skipped`` when not). A step the plan left out
        still runs when the optimiser left time for it (it stopped early, or the estimates were high)."""
        why = self.budget.skip_reason(self.needed(name))
        if why is None:
            self.skipped.pop(name, None)
        else:
            self.skipped[name] = why
        return why is None
