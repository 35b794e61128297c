"""The splat's time budget as an upper bound: each step's seconds predicted before it runs."""

from __future__ import annotations


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
