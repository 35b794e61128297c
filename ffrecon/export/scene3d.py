"""The report's interactive 3D view: cameras of every estimate and a downsampled point cloud, as a plotly
figure whose JavaScript is inlined, so that report.html stays one file that opens offline.

Everything is drawn in the frame of the final cameras (``sparse/0``, the frame of ``points.ply``); the
feed-forward and COLMAP cameras are brought into it by a Sim(3) fitted on the camera centres the two
sets share (:func:`ffrecon.geometry.alignment.umeyama`), as the report's pose comparison does.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
import plotly.graph_objects as go
import pycolmap

from ffrecon.geometry.alignment import umeyama
from ffrecon.geometry.poses import camera_centers, invert_pose
from ffrecon.sfm.colmap_io import cam_from_world_by_name, cameras_by_name

MAX_POINTS = 20_000  # enough to read the scene's shape; keeps the inline figure to ~1 MB
# One colour per estimate, the same in the report's 3D view and in `ffrecon view`.
ESTIMATE_COLOURS = {"final": "#2ca02c", "feed-forward": "#ff7f0e", "COLMAP": "#1f77b4"}
DISAGREEING_COLOUR = "#d62728"
# Where each estimate's COLMAP model lies in an output folder (CONTRACTS.md, section 3).
ESTIMATE_MODELS = {"final": "sparse/0", "feed-forward": "feedforward/sparse", "COLMAP": "colmap/sparse/0"}


@dataclass(frozen=True)
class CameraSet:
    """One estimate's cameras, in the final cameras' frame."""

    label: str
    names: list[str]
    world_from_cam: np.ndarray  # [N, 4, 4], OpenCV camera axes
    K: np.ndarray  # [N, 3, 3] for images of size_wh
    size_wh: np.ndarray  # [N, 2] int


def load_camera_sets(run_dir: Path, names: list[str]) -> list[CameraSet]:
    """The estimates found in ``run_dir`` (final first), each aligned to the final cameras' frame.

    Without ``sparse/0`` (a run without a model), COLMAP's cameras are the final ones.

    A set is left out when its model is missing, or when it shares fewer than 3 registered cameras with
    the final set (a Sim(3) needs three). Returns [] without final cameras.
    """
    models = {label: Path(run_dir) / rel for label, rel in ESTIMATE_MODELS.items()}
    if not _is_model(models["final"]):  # a run without a model: COLMAP's cameras are the final ones
        models["final"] = models.pop("COLMAP")
    loaded = {}
    for label, path in models.items():
        if _is_model(path):
            rec = pycolmap.Reconstruction(str(path))
            poses, registered = cam_from_world_by_name(rec, names)
            cams = cameras_by_name(rec, names)
            keep = [k for k in range(len(names)) if registered[k] and cams[k] is not None]
            loaded[label] = (keep, poses, cams)
    if "final" not in loaded:
        return []
    final_keep, final_poses, _ = loaded["final"]
    final_centers = dict(zip(final_keep, camera_centers(final_poses[final_keep])))
    sets = []
    for label, (keep, poses, cams) in loaded.items():
        shared = [k for k in keep if k in final_centers]
        if len(shared) < 3:
            continue
        # Sim(3) final_from_estimate on the shared centres (identity, up to rounding, for the final set).
        fit = umeyama(camera_centers(poses[shared]), np.array([final_centers[k] for k in shared]))
        world_from_cam = np.array([invert_pose(fit.transform_cam_from_world(poses[k])) for k in keep])  # [N, 3, 4]
        sets.append(
            CameraSet(
                label,
                [names[k] for k in keep],
                _homogeneous(world_from_cam),
                np.array([cams[k].K for k in keep]),
                np.array([(cams[k].width, cams[k].height) for k in keep]),
            )
        )
    return sets


def _is_model(path: Path) -> bool:
    return (path / "images.bin").is_file() or (path / "images.txt").is_file()


def _homogeneous(poses: np.ndarray) -> np.ndarray:
    if poses.shape[-2:] == (4, 4):
        return poses
    out = np.tile(np.eye(4), (len(poses), 1, 1))
    out[:, :3, :] = poses
    return out


def frustum_lines(camera: CameraSet, depth: float) -> np.ndarray:
    """``[N * 17, 3]`` polyline vertices of each camera's frustum (apex to the four image corners at
    ``depth``, then the image rectangle), cameras separated by a row of NaN (plotly's line break).

    The corners are the outer edges of the image: pixel (0, 0) to (w, h) under COLMAP's pixel-centre
    rule (the top-left pixel's centre is (0.5, 0.5)).
    """
    rows = []
    for world_from_cam, K, (w, h) in zip(camera.world_from_cam, camera.K, camera.size_wh):
        corners_px = np.array([[0, 0, 1], [w, 0, 1], [w, h, 1], [0, h, 1]], float)
        rays = corners_px @ np.linalg.inv(K).T * depth  # camera frame, z = depth
        corners = rays @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]
        apex = world_from_cam[:3, 3]
        c0, c1, c2, c3 = corners
        rows.append(np.array([c0, apex, c1, c2, apex, c3, c0, c1, c2, c3, apex]))
        rows.append(np.full((1, 3), np.nan))
    return np.concatenate(rows) if rows else np.zeros((0, 3))


def read_points(path: Path, limit: int = MAX_POINTS, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``(xyz [M, 3], rgb [M, 3] in [0, 1])`` of a point cloud file without its far outliers (outside the
    2-98 % box of each axis grown by a quarter), randomly thinned to ``limit``."""
    cloud = o3d.io.read_point_cloud(str(path))
    xyz, rgb = np.asarray(cloud.points), np.asarray(cloud.colors)
    if len(rgb) != len(xyz):
        rgb = np.full_like(xyz, 0.5)
    if len(xyz) >= 50:  # a few far-off points would otherwise set the view's bounds and shrink the scene
        lo, hi = np.quantile(xyz, [0.02, 0.98], axis=0)
        margin = 0.25 * (hi - lo)
        inside = np.all((xyz >= lo - margin) & (xyz <= hi + margin), axis=1)
        xyz, rgb = xyz[inside], rgb[inside]
    if len(xyz) > limit:
        pick = np.sort(np.random.default_rng(seed).choice(len(xyz), limit, replace=False))
        xyz, rgb = xyz[pick], rgb[pick]
    return xyz, rgb


def scene_figure(
    sets: list[CameraSet], points: tuple[np.ndarray, np.ndarray] | None, disagreeing: set[str]
) -> go.Figure:
    """The 3D figure: the point cloud, each estimate's frustums (final) or centres (the others), and the
    frames named in ``disagreeing`` drawn in red."""
    fig = go.Figure()
    final = next(s for s in sets if s.label == "final")
    centers = final.world_from_cam[:, :3, 3]
    extent = float(np.linalg.norm(centers.max(0) - centers.min(0)))
    if points is not None and len(points[0]):
        extent = max(extent, 0.25 * float(np.linalg.norm(np.ptp(points[0], axis=0))))
    extent = extent or 1.0
    if points is not None and len(points[0]):
        xyz, rgb = points
        colours = [f"rgb({r},{g},{b})" for r, g, b in np.clip(rgb * 255, 0, 255).astype(int)]
        fig.add_trace(_scatter(xyz, "points.ply", mode="markers", marker={"size": 1.5, "color": colours}))
    for s in sets:
        colour = ESTIMATE_COLOURS[s.label]
        bad = np.array([n in disagreeing for n in s.names])
        if s.label == "final":
            for mask, name, c in ((~bad, "final cameras", colour), (bad, "disagreeing frames", DISAGREEING_COLOUR)):
                if mask.any():
                    sub = CameraSet(s.label, [], s.world_from_cam[mask], s.K[mask], s.size_wh[mask])
                    lines = frustum_lines(sub, _frustum_depth(centers, extent))
                    fig.add_trace(_scatter(lines, name, mode="lines", line={"color": c, "width": 4}))
        hover = [f"{s.label}: {n}" + (" (disagrees)" if b else "") for n, b in zip(s.names, bad)]
        marker = {"size": 4, "color": [DISAGREEING_COLOUR if b else colour for b in bad]}
        fig.add_trace(_scatter(s.world_from_cam[:, :3, 3], f"{s.label} centres", hover, marker=marker))
    fig.update_layout(
        height=600,
        margin={"l": 0, "r": 0, "t": 0, "b": 0},
        legend={"itemsizing": "constant"},
        scene={"aspectmode": "data", "camera": _viewpoint(final), **{a: {"visible": False} for a in _AXES}},
    )
    return fig


_AXES = ("xaxis", "yaxis", "zaxis")


def _frustum_depth(centers: np.ndarray, extent: float) -> float:
    """Frustums about as deep as neighbouring cameras are apart (so a dense path does not turn into a
    tangle), within 2-8 % of the scene's extent."""
    if len(centers) < 2:
        return 0.08 * extent
    gaps = np.linalg.norm(centers[:, None] - centers[None], axis=-1) + np.diag(np.full(len(centers), np.inf))
    return float(np.clip(0.8 * np.median(gaps.min(1)), 0.02 * extent, 0.08 * extent))


def _viewpoint(final: CameraSet) -> dict:
    """plotly's scene camera. Up is the cameras' mean image-up (people hold cameras upright; OpenCV's
    image-up is -y). The eye looks across the cameras' smallest horizontal spread, from the side they
    look away from, and from above: behind a row of cameras that sweeps along a facade, beside a path
    that walks towards something, obliquely over a ring."""
    up = -final.world_from_cam[:, :3, 1].sum(0)
    up = up / (np.linalg.norm(up) or 1.0)
    centers = final.world_from_cam[:, :3, 3] - final.world_from_cam[:, :3, 3].mean(0)
    flat = centers - np.outer(centers @ up, up)
    across = np.linalg.svd(flat, full_matrices=False)[2][1] if len(centers) >= 3 else np.zeros(3)  # [2] is up
    across = across - up * (across @ up)
    if np.linalg.norm(across) < 1e-6:  # fewer than three cameras, or all in one vertical line
        across = np.cross(up, [1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.cross(up, [0.0, 1.0, 0.0])
    across = across / np.linalg.norm(across)
    if across @ final.world_from_cam[:, :3, 2].mean(0) > 0:
        across = -across
    eye = 1.4 * (across + 0.6 * up)
    return {"up": dict(zip("xyz", up.tolist())), "eye": dict(zip("xyz", eye.tolist()))}


def _scatter(xyz: np.ndarray, name: str, hover: list[str] | None = None, **style) -> go.Scatter3d:
    style.setdefault("mode", "markers")
    return go.Scatter3d(
        x=xyz[:, 0], y=xyz[:, 1], z=xyz[:, 2], name=name, text=hover, hoverinfo="text" if hover else "name", **style
    )


def scene_html(report: dict, run_dir: Path) -> str:
    """The 3D view as an HTML fragment with plotly.js inlined ('' when the run has no final cameras)."""
    run_dir = Path(run_dir)
    sets = load_camera_sets(run_dir, list(report["inputs"]["names"]))
    if not sets:
        return ""
    cloud = run_dir / "points.ply"
    points = read_points(cloud) if cloud.is_file() else None
    disagreeing = {d["name"] for comp in report.get("pose_errors", {}).values() for d in comp["disagreeing"]}
    fig = scene_figure(sets, points, disagreeing)
    config = {"displaylogo": False, "responsive": True}
    return fig.to_html(full_html=False, include_plotlyjs=True, include_mathjax=False, config=config, div_id="scene3d")
