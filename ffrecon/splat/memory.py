"""The CPU splat's memory, and the resolution it trains at to stay within what is free.

One optimisation step renders a training view at full size and back-propagates the L1 + SSIM loss
through it: colour, transmittance and gradient images, the SSIM kernel's moment maps, the per-pair
gradients of the rasteriser. Every view is held as its uint8 photo (a step converts the one it reads;
float16 copies at the coarser levels of the resolution schedule), and each Gaussian
carries its parameters, their gradients and Adam's two moments. Measured on this 2-core machine
(``tools/bench_splat.py --memory``: one step of :func:`ffrecon.splat.optimize.optimize` on 200k
Gaussians, two views, at 1600x1200 to 6400x4800; docs/benchmarks.md, "Very large photos"): the peak
grows by 313 B per pixel of a view (two targets' 24 B included) over 360 MB; at 108 MP full size
that is 34 GB, which is why the issue's 12000x9000 photo was killed at 23 GB.

    peak ~ BASE_BYTES + STEP_BYTES_PER_PIXEL * (largest view) + VIEW_BYTES_PER_PIXEL * (all views)
           + BYTES_PER_GAUSSIAN * optimize.max_gaussians

The splat shrinks its larger views to the longest side whose peak fits ``MEMORY_FRACTION`` of the
memory available (cameras scaled with the images, so the geometry is the same; smaller views are
left as they are); a cap is logged with the flag that avoids it (``--max-image-size``, whose 1600 px
default needs none on any machine with a few GB free for up to about a hundred views). GPU memory
(gsplat) is not modelled: there the views stay at full size.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

from ffrecon.errors import ResourceError
from ffrecon.machine import available_memory_bytes
from ffrecon.types import capped_size

log = logging.getLogger("ffrecon.splat")

BASE_BYTES = 700 * 2**20  # torch, numba's kernels and the process before the first step (measured 640-990 MB)
STEP_BYTES_PER_PIXEL = 300  # one step at the largest view's size (fit: 313 B/px with two 12 B/px targets)
VIEW_BYTES_PER_PIXEL = 6  # each view: its uint8 photo (3 B/px, the target itself), its float16 coarser levels
BYTES_PER_GAUSSIAN = 2000  # parameters, gradients, Adam moments, projection (fit: 360 MB over 200k)
MEMORY_FRACTION = 0.7  # of the memory available when the splat starts (as the model's chunk size)
MIN_TRAIN_SIDE = 256  # a splat trained below this long side is not worth making: refuse instead
MAX_FACTOR = 64


def splat_peak_bytes(sizes_wh: Sequence[tuple[int, int]], max_gaussians: int, max_side: int | None = None) -> float:
    """Estimated peak of the CPU splat on views of ``sizes_wh`` whose long side is capped at ``max_side``."""
    pixels = [w * h for w, h in (capped_size(w, h, max_side) for w, h in sizes_wh)]
    if not pixels:
        return float(BASE_BYTES)
    return (
        BASE_BYTES
        + STEP_BYTES_PER_PIXEL * max(pixels)
        + VIEW_BYTES_PER_PIXEL * sum(pixels)
        + (BYTES_PER_GAUSSIAN * max_gaussians)
    )


def training_side(
    sizes_wh: Sequence[tuple[int, int]], max_gaussians: int, *, available: float | None = None
) -> int | None:
    """The long side (px) to which the CPU splat must shrink its larger views to fit memory; None: full size.

    Tried from the longest view's side down, by whole fractions of it (1/2, 1/3, ...), never below
    ``MIN_TRAIN_SIDE``; views already shorter than the cap are left as they are. Raises
    :class:`ResourceError` when even the smallest cap does not fit (the run says so before any work:
    :func:`ffrecon.splat.stage.check_splat_memory`).
    """
    free = available_memory_bytes() if available is None else available
    budget = MEMORY_FRACTION * free
    longest = max((max(s) for s in sizes_wh), default=0)
    coarsest = max(1, min(MAX_FACTOR, longest // MIN_TRAIN_SIDE))
    for factor in range(1, coarsest + 1):
        side = None if factor == 1 else longest // factor
        if splat_peak_bytes(sizes_wh, max_gaussians, side) <= budget:
            return side
    need = splat_peak_bytes(sizes_wh, max_gaussians, longest // coarsest)
    raise ResourceError(
        f"the splat needs about {need / 2**30:.1f} GB even with its views at {longest // coarsest} px on the "
        f"long side ({len(sizes_wh)} views, up to {max_gaussians} Gaussians); {free / 2**30:.1f} GB is free",
        "free memory (close other programs), pass fewer photos, or pass --no-splat",
    )
