"""The report's interactive 3D view: cameras of every estimate and a downsampled point cloud, as a plotly
figure whose JavaScript is inlined, so that report.html stays one file that opens offline.

The folder is read as ``ffrecon view`` reads it (:func:`ffrecon.view.scene.load_scene`): everything in
the frame of the final cameras (``sparse/0``, the frame of ``points.ply``), the feed-forward and COLMAP
cameras moved into it by a Sim(3) fitted on the camera centres, the same colours, the same flagged
frames.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import plotly.graph_objects as go
import plotly.io as pio

from ffrecon.colmap_io import is_model_dir
from ffrecon.errors import InputError
from ffrecon.view.scene import FLAG_COLOR, CameraLayer, CameraSpec, Estimate, PointLayer, ViewOptions, load_scene

logger = logging.getLogger("ffrecon.export")
MAX_POINTS = 20_000  # enough to read the scene's shape; keeps the inline figure to ~1 MB


def _css(rgb: tuple[int, int, int]) -> str:
    return "rgb({},{},{})".format(*rgb)


def frustum_lines(cameras: Sequence[CameraSpec], depth: float) -> np.ndarray:
    """``[N * 12, 3]`` polyline vertices of each camera's frustum (apex to the four image corners at
    ``depth``, then the image rectangle), cameras separated by a row of NaN (plotly's line break).

    The corners are the outer edges of the image: pixel (0, 0) to (w, h) under COLMAP's pixel-centre
    rule (the top-left pixel's centre is (0.5, 0.5)).
    """
    rows = []
    for cam in cameras:
        w, h = cam.size_wh
        corners_px = np.array([[0, 0, 1], [w, 0, 1], [w, h, 1], [0, h, 1]], float)
        rays = corners_px @ np.linalg.inv(cam.K).T * depth  # camera frame, z = depth
        corners = rays @ cam.world_from_cam[:3, :3].T + cam.world_from_cam[:3, 3]
        apex = cam.world_from_cam[:3, 3]
        c0, c1, c2, c3 = corners
        rows.append(np.array([c0, apex, c1, c2, apex, c3, c0, c1, c2, c3, apex]))
        rows.append(np.full((1, 3), np.nan))
    return np.concatenate(rows) if rows else np.zeros((0, 3))


def without_far_points(points: PointLayer) -> tuple[np.ndarray, np.ndarray]:
    """``(xyz [M, 3], rgb [M, 3] uint8)`` without the far outliers (outside the 2-98 % box of each axis
    grown by a quarter): a few far-off points would otherwise set the view's bounds and shrink the scene."""
    xyz, rgb = points.xyz, points.rgb
    if len(xyz) >= 50:
        lo, hi = np.quantile(xyz, [0.02, 0.98], axis=0)
        margin = 0.25 * (hi - lo)
        inside = np.all((xyz >= lo - margin) & (xyz <= hi + margin), axis=1)
        xyz, rgb = xyz[inside], rgb[inside]
    return xyz, rgb


def scene_figure(main: CameraLayer, others: Sequence[CameraLayer], points: PointLayer | None) -> dict:
    """The 3D figure, as plotly's figure dict: a sample of the points, ``main``'s cameras as frustums, the
    ``others``' camera centres (already in ``main``'s frame), and flagged frames in red, in the viewer's colours.

    The points' colours join the dict after plotly has built it: plotly checks a list of colours one string at a
    time, twice (0.9 s for 20,000 points, most of the report's time), and these are ``rgb(r,g,b)`` by
    construction. The dict is the one plotly would have built with them (the same JSON)."""
    fig = go.Figure()
    colours = None
    centers = np.array([c.world_from_cam[:, 3] for c in main.cameras])
    extent = float(np.linalg.norm(np.ptp(centers, axis=0)))
    if points is not None and len(points.xyz):
        xyz, rgb = without_far_points(points)
        extent = max(extent, 0.25 * float(np.linalg.norm(np.ptp(xyz, axis=0))))
        colours = [_css(c) for c in rgb.tolist()]
        fig.add_trace(_scatter(xyz, "points.ply", mode="markers", marker={"size": 1.5}))
    depth = _frustum_depth(centers, extent or 1.0)
    for flagged, name, colour in ((False, f"{main.estimate.label} cameras", main.color), (True, "flagged", FLAG_COLOR)):
        cams = [c for c in main.cameras if c.flagged == flagged]
        if cams:
            line = {"color": _css(colour), "width": 4}
            fig.add_trace(_scatter(frustum_lines(cams, depth), name, mode="lines", line=line))
    for layer in (main, *others):
        hover = [f"{layer.estimate.label}: {c.name}" + (" (flagged)" if c.flagged else "") for c in layer.cameras]
        marker = {"size": 4, "color": [_css(FLAG_COLOR if c.flagged else layer.color) for c in layer.cameras]}
        xyz = np.array([c.world_from_cam[:, 3] for c in layer.cameras])
        fig.add_trace(_scatter(xyz, f"{layer.estimate.label} centres", hover, marker=marker))
    fig.update_layout(
        height=600,
        margin={"l": 0, "r": 0, "t": 0, "b": 0},
        legend={"itemsizing": "constant", "x": 0.0, "y": 1.0},  # top left: the mode bar is top right
        scene={"aspectmode": "data", "camera": _viewpoint(main), **{a: {"visible": False} for a in _AXES}},
    )
    figure = fig.to_dict()
    if colours is not None:  # the points are the first trace; plotly orders a marker's colour before its size
        figure["data"][0]["marker"] = {"color": colours, **figure["data"][0]["marker"]}
    return figure


_AXES = ("xaxis", "yaxis", "zaxis")


def _frustum_depth(centers: np.ndarray, extent: float) -> float:
    """Frustums about as deep as neighbouring cameras are apart (so a dense path does not turn into a
    tangle), within 2-8 % of the scene's extent."""
    if len(centers) < 2:
        return 0.08 * extent
    gaps = np.linalg.norm(centers[:, None] - centers[None], axis=-1) + np.diag(np.full(len(centers), np.inf))
    return float(np.clip(0.8 * np.median(gaps.min(1)), 0.02 * extent, 0.08 * extent))


def _viewpoint(layer: CameraLayer) -> dict:
    """plotly's scene camera. Up is the cameras' mean image-up (people hold cameras upright; OpenCV's
    image-up is -y). The eye looks across the cameras' smallest horizontal spread, from the side they
    look away from, and from above: behind a row of cameras that sweeps along a facade, beside a path
    that walks towards something, obliquely over a ring."""
    world_from_cam = np.array([c.world_from_cam for c in layer.cameras])
    up = -world_from_cam[:, :3, 1].sum(0)
    up = up / (np.linalg.norm(up) or 1.0)
    centers = world_from_cam[:, :3, 3] - world_from_cam[:, :3, 3].mean(0)
    flat = centers - np.outer(centers @ up, up)
    across = np.linalg.svd(flat, full_matrices=False)[2][1] if len(centers) >= 3 else np.zeros(3)  # [2] is up
    across = across - up * (across @ up)
    if np.linalg.norm(across) < 1e-6:  # fewer than three cameras, or all in one vertical line
        across = np.cross(up, [1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.cross(up, [0.0, 1.0, 0.0])
    across = across / np.linalg.norm(across)
    if across @ world_from_cam[:, :3, 2].mean(0) > 0:
        across = -across
    eye = 1.4 * (across + 0.6 * up)
    return {"up": dict(zip("xyz", up.tolist())), "eye": dict(zip("xyz", eye.tolist()))}


def _scatter(xyz: np.ndarray, name: str, hover: list[str] | None = None, **style) -> go.Scatter3d:
    style.setdefault("mode", "markers")
    return go.Scatter3d(
        x=xyz[:, 0], y=xyz[:, 1], z=xyz[:, 2], name=name, text=hover, hoverinfo="text" if hover else "name", **style
    )


def _has_scene(run_dir: Path) -> bool:
    """Whether ``run_dir`` holds something the 3D view draws: a camera model or points.ply."""
    return any(is_model_dir(run_dir / e.folder) for e in Estimate) or (run_dir / "points.ply").is_file()


def scene_html(report: dict, run_dir: Path) -> str:
    """The 3D view of the output folder ``run_dir`` (described by ``report``) as an HTML fragment with
    plotly.js inlined; '' when it holds no cameras or a file in it cannot be read (logged: the rest of the
    report is still written). A run that made no cameras and no points (one stopped by a gate) has no view,
    and that is no news: nothing is logged then."""
    if not _has_scene(Path(run_dir)):
        logger.debug("report: no 3D view: the run made no cameras and no points")
        return ""
    try:
        scene = load_scene(Path(run_dir), ViewOptions(max_points=MAX_POINTS, splat=False), report)
    except InputError as err:
        logger.warning("report: no 3D view: %s", err)
        return ""
    order = (Estimate.FINAL, Estimate.FEEDFORWARD, Estimate.COLMAP)  # the first present sets the frame
    layers = sorted((layer for layer in scene.layers if layer.cameras), key=lambda layer: order.index(layer.estimate))
    if not layers:
        return ""
    fig = scene_figure(layers[0], layers[1:], scene.points)
    config = {"displaylogo": False, "responsive": True}
    options = {"full_html": False, "include_plotlyjs": True, "include_mathjax": False, "div_id": "scene3d"}
    return pio.to_html(fig, validate=False, config=config, **options)
