"""Figures for the report, returned as PNG bytes (matplotlib Agg; no global pyplot state).

Camera paths are drawn top-down: projected onto the plane perpendicular to the scene's up direction,
which by default is estimated from the cameras (the mean of their image-up axes, since people hold
cameras roughly upright) or, failing that, the normal of the best-fit plane of the centres.
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure
from PIL import Image

_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b")


@dataclass(frozen=True)
class PathSeries:
    """Camera centres of one camera set, already aligned into the common (reference) frame."""

    label: str
    centers: np.ndarray  # [N, 3] float, nan rows for frames this set has no pose for


def _plane_axes(points: np.ndarray, up: np.ndarray | None) -> np.ndarray:
    """``[2, 3]`` orthonormal axes of the drawing plane (perpendicular to ``up``)."""
    centred = points - points.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=True) if len(points) >= 3 else (None, None, np.eye(3))
    normal = vt[2] if up is None else np.asarray(up, float) / np.linalg.norm(up)
    # First axis: the largest spread within the plane; second completes a right-handed frame.
    for candidate in vt:
        first = candidate - normal * (candidate @ normal)
        if np.linalg.norm(first) > 1e-6:
            break
    first = first / np.linalg.norm(first)
    return np.stack([first, np.cross(normal, first)])


def _to_png(fig: Figure) -> bytes:
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return buf.getvalue()


def camera_paths_png(
    series: Sequence[PathSeries],
    *,
    up: np.ndarray | None = None,
    names: Sequence[str] | None = None,
    highlight: Sequence[int] = (),
    title: str = "Camera paths (top-down, aligned)",
) -> bytes:
    """Top-down plot of several aligned camera paths; ``highlight`` frames are circled and named."""
    valid = [s.centers[np.all(np.isfinite(s.centers), axis=1)] for s in series]
    points = np.concatenate([v for v in valid if len(v)] or [np.zeros((1, 3))])
    axes = _plane_axes(points, up)
    fig = Figure(figsize=(6.0, 5.5))
    ax = fig.add_subplot()
    for k, (s, v) in enumerate(zip(series, valid)):
        if not len(v):
            continue
        xy = s.centers @ axes.T  # nan rows stay nan and break the line there
        colour = _COLOURS[k % len(_COLOURS)]
        ax.plot(xy[:, 0], xy[:, 1], "-", color=colour, lw=1.2, alpha=0.8)
        ax.plot(xy[:, 0], xy[:, 1], "o", color=colour, ms=3.5, label=f"{s.label} ({len(v)})")
        if k == 0 and len(v):
            first = np.flatnonzero(np.all(np.isfinite(s.centers), axis=1))[0]
            ax.annotate("start", xy[first], textcoords="offset points", xytext=(4, 4), fontsize=7)
    if highlight and len(series):
        ref = series[0].centers @ axes.T
        for i in highlight:
            if np.all(np.isfinite(ref[i])):
                ax.plot(*ref[i], "o", mfc="none", mec="red", ms=11, mew=1.5)
                if names is not None:
                    ax.annotate(names[i], ref[i], textcoords="offset points", xytext=(6, -10), fontsize=7, color="red")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8, loc="best")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return _to_png(fig)


def error_bars_png(
    names: Sequence[str],
    rotation_deg: Mapping[str, np.ndarray],
    center_error: Mapping[str, np.ndarray],
    *,
    rotation_threshold_deg: float | None = None,
    center_threshold: float | None = None,
    center_unit: str = "reference units",
    title: str = "Per-image pose error (rotations aligned by their best common rotation, centres by Sim(3))",
) -> bytes:
    """Two panels of grouped bars per image (one group per label); missing values are marked x."""
    n = len(names)
    fig = Figure(figsize=(max(6.0, 0.28 * n + 2.0), 5.0))
    panels = (
        (rotation_deg, "rotation error [deg]", rotation_threshold_deg),
        (center_error, f"centre error [{center_unit}]", center_threshold),
    )
    x = np.arange(n)
    for row, (data, ylabel, threshold) in enumerate(panels, start=1):
        ax = fig.add_subplot(2, 1, row)
        width = 0.8 / max(len(data), 1)
        for k, (label, values) in enumerate(data.items()):
            values = np.asarray(values, float)
            offset = (k - (len(data) - 1) / 2) * width
            _bars(ax, x + offset, np.nan_to_num(values, nan=0.0), width, _COLOURS[k % len(_COLOURS)], label)
            missing = ~np.isfinite(values)
            if missing.any():
                ax.plot(x[missing] + offset, np.zeros(missing.sum()), "x", color="red", ms=6)
        if threshold is not None:
            ax.axhline(threshold, color="red", lw=1, ls="--", label="disagreement threshold")
        ax.set_ylabel(ylabel, fontsize=8)
        ax.set_xlim(-0.5, n - 0.5)
        # names under the lower panel only: a tick is a costly artist, and a 96-frame run has 96 of them a panel
        ax.set_xticks(x if row == 2 else [])
        if row == 2:
            ax.set_xticklabels(names, rotation=90, fontsize=6)
        ax.grid(axis="y", alpha=0.3)
        if row == 1:
            ax.set_title(title, fontsize=10)
            ax.legend(fontsize=7, loc="upper right")  # "best" tests the legend against every bar
    fig.tight_layout()
    return _to_png(fig)


def _bars(ax, x: np.ndarray, heights: np.ndarray, width: float, colour: str, label: str) -> None:
    """Bars from 0 to ``heights`` centred at ``x``, drawn as one collection: ``Axes.bar`` makes an artist per bar
    (tools/bench_report_chart.py: a chart of three camera sets, 96 frames 1.1-1.6 CPU s with them, 0.7-1.0 with
    collections; 250 frames 3.2-4.2 and 2.0-2.1; a loaded 2-core machine)."""
    left, right, zero = x - width / 2, x + width / 2, np.zeros_like(heights)
    rects = np.stack([np.stack([left, left, right, right], -1), np.stack([zero, heights, heights, zero], -1)], -1)
    ax.add_collection(PolyCollection(rects, facecolors=colour, edgecolors="none", label=label))
    ax.update_datalim(np.stack([np.concatenate([left, right]), np.concatenate([zero, heights])], -1))
    ax.autoscale_view()


def thumbnail_png(image: np.ndarray, *, max_side: int = 160) -> bytes:
    """PNG bytes of an ``[H, W, 3]`` uint8 RGB image shrunk to ``max_side`` (never enlarged)."""
    pil = Image.fromarray(np.asarray(image, np.uint8))
    pil.thumbnail((max_side, max_side))
    buf = io.BytesIO()
    pil.save(buf, format="PNG")
    return buf.getvalue()


def timings_png(seconds: dict[str, float], reused: set[str] = frozenset()) -> bytes:
    """Horizontal bars of seconds per stage (matplotlib Agg, no global pyplot state); reused stages hatched."""
    names = list(seconds)[::-1]
    fig = Figure(figsize=(6.0, 0.45 * len(names) + 0.9))
    ax = fig.add_subplot()
    colours = ["#9aa0a6" if n in reused else "#1f77b4" for n in names]
    ax.barh(names, [seconds[n] for n in names], color=colours)
    for y, n in enumerate(names):
        label = f"{seconds[n]:.1f} s" + (" (reused)" if n in reused else "")
        ax.annotate(label, (seconds[n], y), xytext=(4, 0), textcoords="offset points", va="center", fontsize=8)
    ax.set_xlabel("seconds")
    ax.set_title("Time per stage", fontsize=10)
    ax.margins(x=0.2)
    fig.tight_layout()
    return _to_png(fig)


def curves_png(curves: dict[str, list[dict]]) -> bytes:
    """Held-out PSNR and SSIM against optimisation seconds, one line per splat (matplotlib Agg)."""
    fig = Figure(figsize=(8.0, 3.2))
    for col, (key, label) in enumerate((("psnr", "held-out PSNR (dB)"), ("ssim", "held-out SSIM")), start=1):
        ax = fig.add_subplot(1, 2, col)
        for name, points in curves.items():
            ax.plot([p["seconds"] for p in points], [p[key] for p in points], "-o", ms=3, label=name)
        ax.set_xlabel("optimisation seconds")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    return _to_png(fig)
