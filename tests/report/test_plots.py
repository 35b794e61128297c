"""Report figures (ffrecon.report.plots): valid PNGs of the expected size, correct top-down axes."""

from __future__ import annotations

import io

import numpy as np
from PIL import Image

from ffrecon.geometry.poses import look_at_cam_from_world, up_from_cameras
from ffrecon.report.plots import (
    PathSeries,
    _plane_axes,
    camera_paths_png,
    error_bars_png,
    thumbnail_png,
)


def _png(data: bytes) -> Image.Image:
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return Image.open(io.BytesIO(data))


def test_top_down_axes_are_perpendicular_to_up():
    angles = np.linspace(0, 2 * np.pi, 10, endpoint=False)
    centers = np.stack([np.cos(angles), np.sin(angles), np.full(10, 1.5)], 1)
    poses = np.stack([look_at_cam_from_world(c, np.zeros(3)) for c in centers])
    up = up_from_cameras(poses)
    assert up @ np.array([0.0, 0.0, 1.0]) > 0.8  # cameras tilted down, but their image-up points up
    axes = _plane_axes(centers, np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(axes @ axes.T, np.eye(2), atol=1e-9)
    np.testing.assert_allclose(axes[:, 2], 0.0, atol=1e-9)
    # Without an up direction the plane of the ring is found.
    np.testing.assert_allclose(np.abs(np.cross(*_plane_axes(centers, None))), [0, 0, 1], atol=1e-9)


def test_figures_are_pngs():
    rng = np.random.default_rng(0)
    ref = rng.normal(size=(8, 3))
    est = ref + 0.05 * rng.normal(size=(8, 3))
    est[3] = np.nan  # not registered
    paths = camera_paths_png(
        [PathSeries("colmap", ref), PathSeries("feedforward", est)], names=[f"f{i}" for i in range(8)], highlight=[2]
    )
    assert _png(paths).size == (600, 550)
    names = [f"frame_{i:03d}.png" for i in range(8)]
    bars = error_bars_png(
        names,
        {"feedforward": rng.uniform(0, 3, 8), "refined": np.r_[rng.uniform(0, 0.1, 7), np.nan]},
        {"feedforward": rng.uniform(0, 0.1, 8), "refined": rng.uniform(0, 0.01, 8)},
        rotation_threshold_deg=5.0,
    )
    assert _png(bars).size[1] == 500
    thumb = _png(thumbnail_png(rng.integers(0, 255, (240, 320, 3), dtype=np.uint8), max_side=160))
    assert thumb.size == (160, 120)
