"""What the viewer draws, built from an output folder without a browser (pure data, testable).

The estimates live in different frames: the final model (``sparse/0``) defines the viewer's world frame,
the points and the splat are already in it, and every other estimate (feed-forward, COLMAP) is moved
into it by the Sim(3) that best fits its camera centres onto the final ones (Umeyama, least squares).
"""

from __future__ import annotations

import enum
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ffrecon.errors import InputError
from ffrecon.geometry.alignment import Sim3, umeyama
from ffrecon.geometry.poses import invert_pose
from ffrecon.geometry.rotations import quat_xyzw_to_matrix

FLAG_COLOR = (220, 20, 20)  # cameras the cross-check flags, in every layer


class Estimate(enum.Enum):
    """The camera estimates an output folder can hold, with where they live and how they are drawn."""

    FEEDFORWARD = ("feed-forward", "feedforward/sparse", (255, 140, 0))
    COLMAP = ("COLMAP", "crosscheck/sparse/0", (30, 110, 255))  # the independent cross-check
    FINAL = ("final", "sparse/0", (0, 170, 70))

    def __init__(self, label: str, folder: str, color: tuple[int, int, int]) -> None:
        self.label, self.folder, self.color = label, folder, color


@dataclass(frozen=True, kw_only=True)
class ViewOptions:
    max_points: int = 200_000  # points.ply is subsampled to at most this many points
    max_gaussians: int = 100_000  # splat.ply is subsampled (most opaque first) to at most this many
    seed: int = 0  # for the point subsample
    splat: bool = True  # False: splat.ply is not read (the report's 3D view draws cameras and points only)

    def __post_init__(self) -> None:
        for name in ("max_points", "max_gaussians"):
            if getattr(self, name) < 1:
                raise InputError(f"{name} is {getattr(self, name)}, expected at least 1", "pass a positive cap")


@dataclass(frozen=True)
class CameraSpec:
    """One frustum: ``world_from_cam`` ``[3, 4]`` in the viewer's (final) frame, OpenCV axes."""

    name: str
    world_from_cam: np.ndarray
    flagged: bool
    K: np.ndarray  # [3, 3] pinhole intrinsics for an image of size_wh (COLMAP's pixel-centre rule)
    size_wh: tuple[int, int]

    @property
    def fov_y(self) -> float:
        """Vertical field of view, radians."""
        return 2.0 * math.atan2(self.size_wh[1] / 2.0, float(self.K[1, 1]))

    @property
    def aspect(self) -> float:
        """Width / height."""
        return self.size_wh[0] / self.size_wh[1]


@dataclass(frozen=True)
class CameraLayer:
    estimate: Estimate
    cameras: tuple[CameraSpec, ...]
    final_from_layer: Sim3  # how the layer's model was moved into the viewer's frame
    alignment_rms: float  # RMS camera-centre residual of that fit, viewer-frame units (0 for the final layer)

    @property
    def color(self) -> tuple[int, int, int]:
        return self.estimate.color


@dataclass(frozen=True)
class PointLayer:
    xyz: np.ndarray  # [N, 3] float32, viewer frame
    rgb: np.ndarray  # [N, 3] uint8
    total: int  # points in the file before subsampling


@dataclass(frozen=True)
class SplatLayer:
    centers: np.ndarray  # [N, 3] float32, viewer frame
    covariances: np.ndarray  # [N, 3, 3] float32, R diag(scale^2) R^T
    rgbs: np.ndarray  # [N, 3] float32 in [0, 1], the DC colour
    opacities: np.ndarray  # [N, 1] float32 in [0, 1]
    total: int  # Gaussians in the file before subsampling


@dataclass(frozen=True)
class ImageInfo:
    """What the report says about one photo: its status, why it is flagged (empty: not), its pose errors."""

    name: str
    path: Path | None  # OUT/images/<name>, None when absent
    status: str = ""
    why: str = ""
    flags: tuple[str, ...] = ()
    errors: dict = field(default_factory=dict)  # comparison key -> {"rotation_deg": .., "center_error": ..}


@dataclass(frozen=True)
class ViewScene:
    out_dir: Path
    layers: tuple[CameraLayer, ...]
    points: PointLayer | None
    splat: SplatLayer | None
    images: dict[str, ImageInfo]
    missing: tuple[tuple[str, str], ...]  # (layer, why it is not shown)
    notes: tuple[str, ...] = ()

    @property
    def flagged(self) -> tuple[str, ...]:
        return tuple(name for name, info in self.images.items() if info.flags)

    def layer(self, estimate: Estimate) -> CameraLayer | None:
        return next((layer for layer in self.layers if layer.estimate is estimate), None)

    def centers(self) -> np.ndarray:
        """``[M, 3]`` camera centres of every layer (for framing the view)."""
        cams = [c.world_from_cam[:, 3] for layer in self.layers for c in layer.cameras]
        return np.array(cams).reshape(-1, 3)

    def up(self) -> np.ndarray:
        """The world up direction: minus the mean camera y axis (OpenCV y points down)."""
        ys = [c.world_from_cam[:, 1] for layer in self.layers for c in layer.cameras]
        up = -np.mean(ys, axis=0) if ys else np.array([0.0, 0.0, 1.0])
        return up / max(float(np.linalg.norm(up)), 1e-12)


def _read_model(out: Path, estimate: Estimate):
    """``(names, [N, 3, 4] cam_from_world, [N] (K [3, 3], (w, h)))`` of the registered images, or None."""
    import pycolmap

    from ffrecon.colmap_io import is_model_dir, pose_from_rigid

    folder = out / estimate.folder
    if not is_model_dir(folder):
        return None
    try:
        rec = pycolmap.Reconstruction(str(folder))
    except Exception as err:  # pycolmap raises plain RuntimeError/ValueError on unreadable files
        raise InputError(
            f"{folder} is not a readable COLMAP model ({err})", f"re-run ffrecon into {out}, or delete {folder}"
        ) from err
    names, poses, intrinsics = [], [], []
    for image in sorted(rec.images.values(), key=lambda im: im.name):
        if not image.has_pose:
            continue
        camera = rec.cameras[image.camera_id]
        names.append(image.name)
        poses.append(pose_from_rigid(image.cam_from_world()))
        intrinsics.append((np.asarray(camera.calibration_matrix(), float), (int(camera.width), int(camera.height))))
    return names, np.array(poses).reshape(-1, 3, 4), intrinsics


def _align(names, world_from_cam, ref: dict[str, np.ndarray]) -> tuple[Sim3, float, str]:
    """Sim(3) ``final_from_layer`` fitted on the camera centres shared with the final model."""
    common = [k for k, n in enumerate(names) if n in ref]
    if len(common) < 3:
        return Sim3.identity(), 0.0, f"only {len(common)} camera(s) shared with the final model: drawn unaligned"
    src = world_from_cam[common, :, 3]
    dst = np.array([ref[names[k]] for k in common])
    if np.linalg.matrix_rank(src - src.mean(0), tol=1e-9) < 2:
        return Sim3.identity(), 0.0, "its shared camera centres are collinear: drawn unaligned"
    fit = umeyama(src, dst)
    rms = float(np.sqrt(np.mean(np.sum((fit.apply(src) - dst) ** 2, axis=1))))
    return fit, rms, ""


def _load_report(out: Path) -> dict | None:
    path = out / "report.json"
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise InputError(f"{path} is not valid JSON ({err})", f"re-run ffrecon into {out}") from err


def image_flags(report: dict | None) -> dict[str, list[str]]:
    """Why each photo is flagged, from report.json: its feed-forward and COLMAP poses disagree beyond the
    cross-check's thresholds, COLMAP did not register it, or the evidence rejected or replaced its pose."""
    flags: dict[str, list[str]] = {}
    if not report:
        return flags
    for key, comparison in (report.get("pose_errors") or {}).items():
        if key.endswith("_vs_colmap"):
            for item in comparison.get("disagreeing", []):
                flags.setdefault(item["name"], []).append(f"{comparison['estimate']} vs COLMAP: {item['reason']}")
    colmap = report.get("colmap") or {}
    for name in colmap.get("unregistered", []) if "skipped" not in colmap else []:
        flags.setdefault(name, []).append("COLMAP did not register it")
    evidence = report.get("evidence") or {}
    for item in evidence.get("per_image", []):
        if item.get("verdict", "confirmed") != "confirmed" or item["status"] == "COLMAP only":
            label = f"{item['verdict']} ({item['status']})" if "verdict" in item else item["status"]
            flags.setdefault(item["name"], []).append(f"{label}: {item['why']}")
    return flags


def _image_infos(out: Path, report: dict | None, names: set[str]) -> dict[str, ImageInfo]:
    flags = image_flags(report)
    evidence = {e["name"]: e for e in ((report or {}).get("evidence") or {}).get("per_image", [])}
    errors: dict[str, dict] = {}
    for key, comparison in ((report or {}).get("pose_errors") or {}).items():
        for name, values in (comparison.get("per_image") or {}).items():
            errors.setdefault(name, {})[key] = values
    infos = {}
    for name in sorted(names | set(flags) | set(evidence)):
        path = out / "images" / name
        ev = evidence.get(name, {})
        infos[name] = ImageInfo(
            name,
            path if path.is_file() else None,
            ev.get("status", ""),
            ev.get("why", ""),
            tuple(flags.get(name, ())),
            errors.get(name, {}),
        )
    return infos


def _read_points(path: Path, options: ViewOptions) -> PointLayer:
    import open3d as o3d

    cloud = o3d.io.read_point_cloud(str(path))
    xyz = np.asarray(cloud.points, dtype=np.float32)
    if len(xyz) == 0 or not np.isfinite(xyz).all():
        raise InputError(f"{path} holds no readable points", f"re-run ffrecon, or delete {path.name}")
    rgb = np.asarray(cloud.colors) if cloud.has_colors() else np.full((len(xyz), 3), 0.6)
    keep = np.arange(len(xyz))
    if len(xyz) > options.max_points:
        keep = np.sort(np.random.default_rng(options.seed).choice(len(xyz), options.max_points, replace=False))
    rgb8 = np.clip(np.round(rgb[keep] * 255), 0, 255).astype(np.uint8)
    return PointLayer(xyz[keep], rgb8, len(xyz))


def splat_layer(gaussians, max_gaussians: int) -> SplatLayer:
    """Centres, covariances ``R diag(exp(2 log_scale)) R^T``, DC colours and opacities of the most opaque
    ``max_gaussians`` Gaussians (all of them when there are fewer)."""
    g = gaussians.detached().to("cpu")
    logits = g.opacity_logits.double().numpy().reshape(-1)
    keep = np.argsort(-logits, kind="stable")[:max_gaussians]
    quats_wxyz = g.quats_wxyz.double().numpy()[keep]
    rot = quat_xyzw_to_matrix(quats_wxyz[:, [1, 2, 3, 0]])  # normalised there
    cov = (rot * np.exp(2.0 * g.log_scales.double().numpy()[keep])[:, None, :]) @ rot.transpose(0, 2, 1)
    return SplatLayer(
        g.means.numpy()[keep].astype(np.float32),
        cov.astype(np.float32),
        g.colors_dc().numpy()[keep].astype(np.float32),
        (1.0 / (1.0 + np.exp(-logits[keep])))[:, None].astype(np.float32),
        len(g),
    )


def _read_splat(path: Path, options: ViewOptions) -> SplatLayer:
    from ffrecon.formats.splat_ply import read_splat_ply

    fix = f"re-run the splat stage (ffrecon run ... --resume), or delete {path.name} to view without it"
    try:
        gaussians = read_splat_ply(path)
    except InputError as err:
        raise InputError(f"splat.ply is corrupt: {err.problem}", fix) from err
    except (ValueError, OSError, UnicodeDecodeError) as err:  # truncated data, bad header numbers
        raise InputError(f"{path} is corrupt or truncated ({err})", fix) from err
    layer = splat_layer(gaussians, options.max_gaussians)
    arrays = {"centres": layer.centers, "covariances": layer.covariances, "colours": layer.rgbs}
    bad = [k for k, v in arrays.items() if not np.isfinite(v).all()]
    if len(layer.centers) == 0 or bad:
        raise InputError(f"{path} has {'no Gaussians' if not bad else 'non-finite ' + ', '.join(bad)}", fix)
    return layer


def load_scene(out_dir: Path, options: ViewOptions = ViewOptions(), report: dict | None = None) -> ViewScene:
    """Read an ffrecon output folder into the layers the viewer draws (see the module docstring for frames).

    ``report``: the folder's report data when the caller has it (the report writer); else report.json is read.

    Raises:
        InputError: ``out_dir`` is missing or holds no ffrecon output, or one of its files is unreadable.
    """
    out = Path(out_dir)
    if not out.is_dir():
        raise InputError(f"{out} does not exist or is not a folder", "pass the output folder of `ffrecon run -o OUT`")
    models = {e: _read_model(out, e) for e in Estimate}
    if not any(models.values()) and not (out / "points.ply").exists() and not (out / "splat.ply").exists():
        raise InputError(
            f"{out} is not an ffrecon output folder: no sparse/0, feedforward/sparse, crosscheck/sparse/0, "
            "points.ply or splat.ply in it",
            "pass the folder given to `ffrecon run -o OUT` (or `ffrecon demo -o OUT`) after the run finished",
        )
    report = _load_report(out) if report is None else report
    missing, notes = [], []
    if report is None:
        notes.append("no report.json: no camera is flagged")
    order = [Estimate.FINAL, Estimate.FEEDFORWARD, Estimate.COLMAP]
    reference = next((e for e in order if models[e]), None)
    ref_centers = {}
    if reference is not None:
        names, cam_from_world = models[reference][:2]
        ref_centers = {n: invert_pose(p)[:, 3] for n, p in zip(names, cam_from_world)}
    if reference is not None and reference is not Estimate.FINAL:
        notes.append(f"no final model: the {reference.label} cameras define the frame")
    flags = image_flags(report)
    layers, all_names = [], set()
    for estimate in Estimate:
        model = models[estimate]
        if model is None:
            missing.append((f"{estimate.label} cameras", f"no model in {estimate.folder}"))
            continue
        names, cam_from_world, intrinsics = model
        world_from_cam = np.array([invert_pose(p) for p in cam_from_world]).reshape(-1, 3, 4)
        fit, rms, why = (
            (Sim3.identity(), 0.0, "") if estimate is reference else _align(names, world_from_cam, ref_centers)
        )
        if why:
            notes.append(f"{estimate.label} cameras: {why}")
        moved = fit.transform_cam_from_world(cam_from_world)  # cam_from_final, metric part scaled
        cams = tuple(
            CameraSpec(n, invert_pose(p), n in flags, k, wh) for n, p, (k, wh) in zip(names, moved, intrinsics)
        )
        layers.append(CameraLayer(estimate, cams, fit, rms))
        all_names.update(names)
    points = _read_points(out / "points.ply", options) if (out / "points.ply").exists() else None
    if points is None:
        missing.append(("points", "no points.ply"))
    splat = _read_splat(out / "splat.ply", options) if options.splat and (out / "splat.ply").exists() else None
    if splat is None and options.splat:
        missing.append(("splat", "no splat.ply"))
    return ViewScene(
        out, tuple(layers), points, splat, _image_infos(out, report, all_names), tuple(missing), tuple(notes)
    )
