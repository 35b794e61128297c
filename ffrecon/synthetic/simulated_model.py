"""A simulated VGGT-contract ONNX model: a scene's reference cameras and depth plus controlled, realistic error.

No real weights can be downloaded in CI, so the demo and the end-to-end tests run this instead. The
scene is either ffrecon's synthetic room (:class:`~ffrecon.synthetic.scene.SyntheticScene`, exact ground
truth; network-resolution depth is ray-cast) or real photos with a reference reconstruction
(:class:`~ffrecon.synthetic.real_scene.RealScene`; network-resolution depth is bilinearly resampled from
its depth maps, where 0 means unknown and is never interpolated across: such pixels get the frame's
median depth and the lowest confidence, 1). The graph stores, per scene frame, a noisy pose, noisy
intrinsics and a noisy depth map at network resolution. For any subset and order of the scene's frames
it behaves like VGGT:

1. it identifies each input frame by a signature (the frame average-pooled to 8 x 8) and gathers the
   stored outputs of the nearest stored signature;
2. it re-expresses everything in the first input frame's camera (whose pose becomes identity);
3. it normalises the scale per call by the mean distance of all the call's points from the origin
   (the first camera), as VGGT does.

The injected errors (:class:`SimulatedTruth`) are returned so that tests can compare against them.
The model says it is simulated in its metadata: ``metadata_props["ffrecon.simulated"] == "true"``.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import onnx

from ffrecon.checks import check_number
from ffrecon.geometry.poses import camera_centers, compose_poses, invert_pose
from ffrecon.geometry.projection import pixel_centers
from ffrecon.geometry.rotations import axis_angle_to_matrix, matrix_to_quat_xyzw
from ffrecon.models.vggt import PreprocessMode, encode_pose_enc, preprocess_vggt
from ffrecon.synthetic import render
from ffrecon.synthetic.onnx_graph import GraphBuilder, quat_product_basis
from ffrecon.synthetic.real_scene import RealScene
from ffrecon.synthetic.scene import SyntheticScene, scene_geometry
from ffrecon.types import ModelFamily, ModelInfo, PinholeCamera, Prediction

logger = logging.getLogger("ffrecon.synthetic")

SIGNATURE_GRID = 8  # frames are identified by their 8 x 8 average-pooled thumbnails
MAX_DRIFT_SLOTS = 1024  # the longest call a drifting model (SimulationOptions.drift_deg_per_slot) takes
METADATA_KEY = "ffrecon.simulated"
_CONF_MAX = 10.0
_CONF_UNKNOWN = 1.0  # confidence of pixels without reference depth: the contract's minimum
_SYNTHETIC_DOC = (
    "SIMULATED VGGT-contract model built by ffrecon.synthetic.simulated_model: it outputs the ground truth of "
    "one synthetic scene plus injected error, and recognises only that scene's frames. Not a trained network."
)


@dataclass(frozen=True, kw_only=True)
class SimulationOptions:
    rotation_noise_deg: float = 2.5  # per-frame rotation error: random axis, angle uniform in [0.5, 1.5] x this
    translation_noise: float = 0.03  # per-frame centre error (RMS), fraction of the scene distance (mean median depth)
    focal_error: float = 0.03  # relative focal error: one signed value for the model, plus 20% of it per frame
    depth_error: float = 0.03  # std of a smooth multiplicative depth error field (per frame)
    bad_frames: tuple[int, ...] = ()  # frames whose pose is badly wrong
    bad_rotation_deg: float = 20.0  # rotation error of the bad frames (their centre error is 5x too)
    target_size: int = 518  # network width of preprocess_vggt (CROP mode) the model is built for
    seed: int = 0
    # > 1: depth and confidence are stored at 1/depth_stride of the network resolution (area averages) and
    # upsampled bilinearly in the graph, so the model is about depth_stride^2 smaller: at 1 a frame stores
    # 1.6 MB (a thousand frames would pass protobuf's 2 GB limit), at 4 about 0.1 MB. Edges blur over
    # depth_stride network pixels.
    depth_stride: int = 1
    # Drift within a call, as a real model's error grows along a long input: the k-th input frame of a call
    # sees the world turned by k times this about the vertical (world z) through the first input frame's centre.
    # Chunks chained on shared frames accumulate it (about this much per frame of the path); 0: no drift.
    drift_deg_per_slot: float = 0.0
    # Per-frame depth scale error: frame i's whole depth map is scaled by exp(this * N(0, 1)), as a network
    # whose scale is right for the cameras but not for every frame's depth (its confidence does not show it).
    depth_scale_error: float = 0.0

    def __post_init__(self) -> None:
        check_number("SimulationOptions.depth_stride", self.depth_stride, low=1, high=16, integer=True)
        check_number("SimulationOptions.drift_deg_per_slot", self.drift_deg_per_slot, low=0, high=1)
        check_number("SimulationOptions.depth_scale_error", self.depth_scale_error, low=0, high=0.5)


@dataclass(frozen=True)
class SimulatedTruth:
    """What was injected, at the ORIGINAL image resolution, in the ground-truth world frame."""

    cam_from_world: np.ndarray  # [N, 3, 4] float64 noisy poses, OpenCV
    K: np.ndarray  # [N, 3, 3] float64 noisy intrinsics, original pixels
    depth: np.ndarray  # [N, H, W] float32 noisy z-depth
    depth_error: np.ndarray  # [N, H, W] float32 relative error: depth = true depth * (1 + depth_error)


def _depth_field(rng: np.random.Generator, num_terms: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Random smooth field on normalised image coordinates: ``(freqs [K, 2] cycles/image, phases [K])``."""
    angles = rng.uniform(0, 2 * np.pi, num_terms)
    cycles = rng.uniform(0.3, 1.5, num_terms)
    freqs = np.stack([np.cos(angles), np.sin(angles)], axis=1) * cycles[:, None]
    return freqs, rng.uniform(0, 2 * np.pi, num_terms)


def _eval_field(field: tuple[np.ndarray, np.ndarray], xy_norm: np.ndarray) -> np.ndarray:
    """Unit-variance smooth field at ``[..., 2]`` normalised coordinates (x / W, y / H)."""
    freqs, phases = field
    arg = 2 * np.pi * xy_norm @ freqs.T + phases
    return np.cos(arg).sum(-1) * np.sqrt(2.0 / len(phases))


def _inject_pose_error(
    scene: SyntheticScene | RealScene, options: SimulationOptions, rng: np.random.Generator
) -> np.ndarray:
    """``[N, 3, 4]`` noisy cam_from_world in the scene's (reference) world frame."""
    n = len(scene)
    scene_distance = float(np.mean([np.median(d[d > 0]) for d in scene.depth]))  # 0 = unknown (real scenes)
    angles = np.radians(options.rotation_noise_deg) * rng.uniform(0.5, 1.5, n)
    center_err = rng.normal(size=(n, 3)) * options.translation_noise * scene_distance / np.sqrt(3)
    for i in options.bad_frames:
        angles[i] = np.radians(options.bad_rotation_deg)
        center_err[i] *= 5.0
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    rot = axis_angle_to_matrix(axes * angles[:, None]) @ scene.cam_from_world[:, :, :3]
    centers = camera_centers(scene.cam_from_world) + center_err
    return np.concatenate([rot, -np.einsum("nij,nj->ni", rot, centers)[..., None]], axis=2)


def _check_geometry(scene: SyntheticScene, geometry: render.Geometry) -> None:
    """The stored depth must be the synthetic room's (the network-resolution depth is re-cast from it)."""
    h, w = scene.depth.shape[1:]
    rows, cols = np.meshgrid(np.linspace(0, h - 1, 7).astype(int), np.linspace(0, w - 1, 7).astype(int), indexing="ij")
    uv = np.stack([cols.ravel() + 0.5, rows.ravel() + 0.5], 1)  # pixel centres, COLMAP rule
    for i in (0, len(scene) - 1):
        cast = render.cast_depth(geometry, scene.cam_from_world[i], scene.camera.K, uv)
        stored = scene.depth[i][rows.ravel(), cols.ravel()]
        if np.median(np.abs(cast - stored) / stored) > 1e-4:
            raise ValueError("scene depth does not match ffrecon's synthetic room; build the scene with make_scene")


def sample_depth(depth: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear samples of a depth map that never interpolate across unknown pixels.

    ``depth`` ``[H, W]`` z-depth with 0 where unknown; ``uv`` ``[P, 2]`` pixel positions (COLMAP rule:
    the top-left pixel's centre is (0.5, 0.5)), clamped to the outermost pixel centres. Returns ``[P]``
    float64, 0 where a neighbour with non-zero weight is unknown.

    >>> d = np.array([[1.0, 3.0], [0.0, 5.0]])
    >>> sample_depth(d, np.array([[1.0, 0.5], [1.5, 1.0], [1.0, 1.0]])).tolist()
    [2.0, 4.0, 0.0]
    """
    h, w = depth.shape
    x = np.clip(uv[:, 0] - 0.5, 0, w - 1)
    y = np.clip(uv[:, 1] - 0.5, 0, h - 1)
    x0, y0 = np.minimum(x.astype(int), w - 2).clip(0), np.minimum(y.astype(int), h - 2).clip(0)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = x - x0, y - y0
    corners = np.stack([depth[y0, x0], depth[y0, x1], depth[y1, x0], depth[y1, x1]])  # [4, P]
    weights = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy])
    out = (corners * weights).sum(0)
    return np.where(((corners > 0) | (weights == 0)).all(0), out, 0.0)


def _depth_source(scene: SyntheticScene | RealScene) -> Callable[[int, np.ndarray], np.ndarray]:
    """``depth_at(i, uv [P, 2] original pixels) -> [P]`` z-depth of frame ``i``, 0 where unknown.

    The synthetic room is ray-cast (exact at any resolution); a real scene's depth maps are resampled.
    """
    if isinstance(scene, RealScene):
        return lambda i, uv: sample_depth(scene.depth[i], uv)
    geometry = scene_geometry(scene.options.backdrop, scene.options.layout)
    _check_geometry(scene, geometry)
    return lambda i, uv: render.cast_depth(geometry, scene.cam_from_world[i], scene.camera.K, uv)


def simulate(
    scene: SyntheticScene | RealScene, options: SimulationOptions = SimulationOptions()
) -> tuple[SimulatedTruth, dict]:
    """Draw the injected errors and the network-resolution outputs (without writing a model).

    Returns ``(truth, arrays)``; ``arrays`` holds what the graph stores, per scene frame, at network
    resolution: ``batch``, ``signatures``, ``rot``, ``centers``, ``quat_xyzw``, ``fov_hw``, ``inv_focal``,
    ``depth``, ``conf``, ``size_hw``. Pixels without reference depth (real scenes) get the frame's median
    depth and confidence 1 at both resolutions.
    """
    bad = [i for i in options.bad_frames if not 0 <= i < len(scene)]
    if bad:
        raise ValueError(f"bad_frames {bad} outside 0..{len(scene) - 1}")
    rng = np.random.default_rng(options.seed)
    depth_at = _depth_source(scene)
    n, (h, w) = len(scene), scene.depth.shape[1:]
    cam_from_world = _inject_pose_error(scene, options, rng)
    focal_scale = 1 + options.focal_error * (rng.choice([-1.0, 1.0]) + 0.2 * rng.normal(size=n))
    K = np.repeat(scene.camera.K[None], n, axis=0)
    K[:, 0, 0] *= focal_scale
    K[:, 1, 1] *= focal_scale
    fields = [_depth_field(rng) for _ in range(n)]
    # Drawn from a stream of its own, so that every other error stays what the seed gave before.
    scales = np.exp(options.depth_scale_error * np.random.default_rng([options.seed, 39]).standard_normal(n))

    batch, transforms = preprocess_vggt(list(scene.images), mode=PreprocessMode.CROP, target_size=options.target_size)
    t = transforms[0]
    hn, wn = batch.shape[2:]
    orig_uv = pixel_centers(h, w)
    net_uv = (pixel_centers(hn, wn) - [t.offset_x, t.offset_y]) / [t.scale_x, t.scale_y]  # in original pixels
    depth_err = np.empty((n, h, w), np.float32)
    net_depth = np.empty((n, hn, wn), np.float32)
    net_conf = np.empty((n, hn, wn), np.float32)
    for i in range(n):
        depth_err[i] = options.depth_error * _eval_field(fields[i], orig_uv / [w, h])
        if scales[i] != 1.0:
            depth_err[i] = (1 + depth_err[i]) * scales[i] - 1
        err_net = options.depth_error * _eval_field(fields[i], net_uv / [w, h])
        true_net = depth_at(i, net_uv.reshape(-1, 2)).reshape(hn, wn)
        net_depth[i] = true_net * (1 + err_net) * scales[i]
        net_conf[i] = 1 + (_CONF_MAX - 1) * np.exp(-np.abs(err_net) / max(options.depth_error, 1e-6))
        _fill_unknown(net_depth[i], net_conf[i], true_net > 0)
    truth = SimulatedTruth(
        cam_from_world=cam_from_world,
        K=K,
        depth=(scene.depth * (1 + depth_err)).astype(np.float32),
        depth_error=depth_err,
    )
    for i in range(n):
        _fill_unknown(truth.depth[i], None, scene.depth[i] > 0)
    K_net = K.copy()
    K_net[:, 0] *= t.scale_x
    K_net[:, 1] *= t.scale_y
    if options.depth_stride > 1:
        net_depth, net_conf = (_area_downsampled(a, options.depth_stride) for a in (net_depth, net_conf))
    return truth, _stored_arrays(batch, cam_from_world, K_net, net_depth, net_conf) | {
        "drift_deg_per_slot": options.drift_deg_per_slot
    }


def _area_downsampled(maps: np.ndarray, stride: int) -> np.ndarray:
    """``[N, H, W]`` maps area-averaged to ``[N, ceil(H / stride), ceil(W / stride)]``."""
    h, w = maps.shape[1:]
    size = (-(-w // stride), -(-h // stride))
    return np.stack([cv2.resize(m, size, interpolation=cv2.INTER_AREA) for m in maps]).astype(np.float32)


def _fill_unknown(depth: np.ndarray, conf: np.ndarray | None, known: np.ndarray) -> None:
    """In place: unknown pixels of one frame's ``depth`` ``[H, W]`` get the median of its known depth (a
    plausible value that fusion and refinement ignore), and ``conf`` there the contract's minimum, 1."""
    if known.all():
        return  # synthetic scenes: nothing is unknown, and nothing changes
    depth[~known] = np.median(depth[known]) if known.any() else 1.0
    if conf is not None:
        conf[~known] = _CONF_UNKNOWN


def _stored_arrays(
    batch: np.ndarray, cam_from_world: np.ndarray, K_net: np.ndarray, net_depth: np.ndarray, net_conf: np.ndarray
) -> dict:
    """What the graph stores per scene frame (see :func:`simulate`), from the network-resolution
    ``batch [N, 3, Hn, Wn]``, the noisy poses, intrinsics ``K_net [N, 3, 3]`` in network pixels,
    and the noisy depth and confidence ``[N, Hn, Wn]``."""
    n, hn, wn = len(batch), *batch.shape[2:]
    pose_enc = encode_pose_enc(cam_from_world, K_net, (hn, wn))
    g = SIGNATURE_GRID
    kh, kw = hn // g, wn // g
    signatures = batch[:, :, : g * kh, : g * kw].reshape(n, 3, g, kh, g, kw).mean(axis=(3, 5)).reshape(n, -1)
    return {
        "batch": batch,
        "signatures": signatures,
        "rot": cam_from_world[:, :, :3],
        "centers": camera_centers(cam_from_world),
        "quat_xyzw": matrix_to_quat_xyzw(cam_from_world[:, :, :3]),
        "fov_hw": pose_enc[:, 7:9],
        "inv_focal": np.stack([1 / K_net[:, 0, 0], 1 / K_net[:, 1, 1]], axis=1),
        "depth": net_depth,
        "conf": net_conf,
        "size_hw": (hn, wn),
    }


def injected_cam_from_first(truth: SimulatedTruth, frames: list[int]) -> np.ndarray:
    """``[S, 3, 4]`` the injected poses of ``frames`` as cam_from_first (the first listed frame's camera is
    the world), before the model's per-call scale normalisation: what the model's poses equal up to scale."""
    return compose_poses(truth.cam_from_world[frames], invert_pose(truth.cam_from_world[frames[0]]))


def build_simulated_vggt(
    scene: SyntheticScene | RealScene, out_path: Path, options: SimulationOptions = SimulationOptions()
) -> SimulatedTruth:
    """Write the simulated model to ``out_path`` (an ``.onnx`` file) and return the injected errors.

    The model's input is ``input_images [S, 3, Hn, Wn]`` float32 in [0, 1], the scene's frames
    preprocessed by ``preprocess_vggt(images, PreprocessMode.CROP, options.target_size)``, any subset
    in any order; its outputs follow the VGGT contract (docs/contracts.md, "Multi-view models"). A
    24-frame 320x240 scene gives ~40 MB. Input frames are matched to the nearest stored signature, so
    frames that are not the scene's (or preprocessed differently) silently get some scene frame's
    outputs; a different input size is refused by onnxruntime (the size is fixed). For a
    :class:`~ffrecon.synthetic.real_scene.RealScene` the "truth" is its reference reconstruction, and the
    model's doc string and ``ffrecon.scene`` metadata say so.
    """
    truth, arrays = simulate(scene, options)
    model = _build_graph(arrays)
    model.doc_string = scene.description if isinstance(scene, RealScene) else _SYNTHETIC_DOC
    meta = {
        METADATA_KEY: "true",
        "ffrecon.scene": json.dumps({**scene.options.to_dict(), "names": list(scene.names)}),
        "ffrecon.simulation": json.dumps({**asdict(options), "bad_frames": list(options.bad_frames)}),
        "ffrecon.preprocess": json.dumps({"mode": PreprocessMode.CROP.value, "target_size": options.target_size}),
    }
    for key, value in meta.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save_model(model, str(out_path))
    logger.info(
        "wrote simulated VGGT model for %d frames (%dx%d network input) to %s",
        len(scene),
        arrays["size_hw"][1],
        arrays["size_hw"][0],
        out_path,
    )
    return truth


def _full_resolution(g: GraphBuilder, flat: str, stored_hw: tuple[int, int], size_hw: tuple[int, int]) -> str:
    """``[S, Hn * Wn]``: per-frame maps stored flat at ``stored_hw``, bilinearly upsampled to the network's
    ``size_hw`` when smaller (see ``SimulationOptions.depth_stride``)."""
    if tuple(stored_hw) == tuple(size_hw):
        return flat
    maps = g.op("Reshape", [flat, g.const(np.array([-1, 1, *stored_hw], np.int64))])
    first_two = g.op(
        "Slice", [g.op("Shape", [maps]), g.const(np.array([0], np.int64)), g.const(np.array([2], np.int64))]
    )
    sizes = g.op("Concat", [first_two, g.const(np.array(size_hw, np.int64))], axis=0)
    up = g.op("Resize", [maps, "", "", sizes], mode="linear", coordinate_transformation_mode="half_pixel")
    return g.op("Reshape", [up, g.const(np.array([-1, size_hw[0] * size_hw[1]], np.int64))])


def _build_graph(arrays: dict) -> onnx.ModelProto:
    """The ONNX graph described in the module docstring, from :func:`simulate`'s ``arrays``."""
    hn, wn = arrays["size_hw"]
    n = len(arrays["depth"])
    g = GraphBuilder("ffrecon_simulated_vggt")
    x = g.input("input_images", ["S", 3, hn, wn])
    idx = _frame_index(g, x, arrays["signatures"], (hn, wn))  # [S] index of the scene frame

    def gather(name: str, values: np.ndarray) -> str:
        return g.op("Gather", [g.const(values.astype(np.float32), name), idx], axis=0)

    rot, centers, quat = (
        gather("rot", arrays["rot"]),
        gather("centers", arrays["centers"]),
        gather("quat_xyzw", arrays["quat_xyzw"]),
    )
    if arrays.get("drift_deg_per_slot", 0.0) > 0:
        rot, centers, quat = _drifted(g, idx, rot, centers, quat, arrays["drift_deg_per_slot"])
    fov, inv_f = gather("fov_hw", arrays["fov_hw"]), gather("inv_focal", arrays["inv_focal"])
    depth = _full_resolution(g, gather("depth", arrays["depth"].reshape(n, -1)), arrays["depth"].shape[1:], (hn, wn))
    conf = _full_resolution(g, gather("conf", arrays["conf"].reshape(n, -1)), arrays["conf"].shape[1:], (hn, wn))
    zero = g.const(np.array(0, np.int64))
    rot0, center0, quat0 = (g.op("Gather", [v, zero], axis=0) for v in (rot, centers, quat))
    quat_rel = _quat_relative_to_first(g, quat, quat0)
    # Translations: t_rel_i = R_i (c_0 - c_i).
    diff = g.op("Sub", [center0, centers])  # [S, 3]
    last = g.const(np.array([-1], np.int64))
    t_rel = g.op("Squeeze", [g.op("MatMul", [rot, g.op("Unsqueeze", [diff, last])]), last])
    p_rel = _points_in_first_camera(g, rot, rot0, diff, depth, inv_f, last, (hn, wn))  # [S, P, 3]
    # Scale: mean distance of all the call's points from the first camera, as VGGT normalises; so
    # any two calls differ by a similarity, and a chunked run must recover it from shared frames.
    radius = g.op("Sqrt", [g.op("ReduceSum", [g.op("Mul", [p_rel, p_rel]), last], keepdims=0)])  # [S, P]
    inv_scale = g.op("Reciprocal", [g.op("ReduceMean", [radius], axes=[0, 1], keepdims=0)])

    batch0 = g.const(np.array([0], np.int64))
    pose_enc = g.op("Concat", [g.op("Mul", [t_rel, inv_scale]), quat_rel, fov], axis=1)
    g.output(g.op("Unsqueeze", [pose_enc, batch0]), "pose_enc", [1, "S", 9])
    shape5 = g.const(np.array([1, -1, hn, wn, 1], np.int64))
    g.output(g.op("Reshape", [g.op("Mul", [depth, inv_scale]), shape5]), "depth", [1, "S", hn, wn, 1])
    shape4 = g.const(np.array([1, -1, hn, wn], np.int64))
    g.output(g.op("Reshape", [conf, shape4]), "depth_conf", [1, "S", hn, wn])
    shape_pts = g.const(np.array([1, -1, hn, wn, 3], np.int64))
    g.output(g.op("Reshape", [g.op("Mul", [p_rel, inv_scale]), shape_pts]), "world_points", [1, "S", hn, wn, 3])
    # The point head is a little less sure than the depth head.
    point_conf = g.op("Add", [g.op("Mul", [conf, g.const(np.float32(0.8))]), g.const(np.float32(0.2))])
    g.output(g.op("Reshape", [point_conf, shape4]), "world_points_conf", [1, "S", hn, wn])
    g.output(g.op("Unsqueeze", [x, batch0]), "images", [1, "S", 3, hn, wn])
    return g.model(opset=17)


def _drifted(g: GraphBuilder, idx: str, rot: str, centers: str, quat: str, deg_per_slot: float) -> tuple[str, str, str]:
    """``(rot, centers, quat)`` of the call's frames with the drift of ``SimulationOptions.drift_deg_per_slot``:
    slot k's world is turned by ``D_k``, k * deg_per_slot about world z through the first frame's centre, so
    its camera becomes ``R D_k^T`` with centre ``c_0 + D_k (c - c_0)`` (the frame's depth is unchanged)."""
    angles = np.deg2rad(deg_per_slot) * np.arange(MAX_DRIFT_SLOTS)
    turns = np.stack([axis_angle_to_matrix(np.array([0.0, 0.0, a])) for a in angles])  # D_k
    slots = g.op("Range", [g.const(np.array(0, np.int64)), g.op("Size", [idx]), g.const(np.array(1, np.int64))])

    def per_slot(name: str, values: np.ndarray) -> str:
        return g.op("Gather", [g.const(values.astype(np.float32), name), slots], axis=0)

    turns_t = per_slot("drift_turns_t", turns.transpose(0, 2, 1))  # [S, 3, 3] D_k^T
    rot_d = g.op("MatMul", [rot, turns_t])
    center0 = g.op("Gather", [centers, g.const(np.array(0, np.int64))], axis=0)
    one = g.const(np.array([1], np.int64))
    offsets = g.op("Unsqueeze", [g.op("Sub", [centers, center0]), one])  # [S, 1, 3] rows: (c - c_0)^T
    centers_d = g.op("Add", [center0, g.op("Squeeze", [g.op("MatMul", [offsets, turns_t]), one])])
    # q' = q (x) conj(q_D): the product is linear in its second factor, q' = q @ M(conj(q_D)) per slot.
    conj = matrix_to_quat_xyzw(turns) * np.array([-1, -1, -1, 1])
    basis = quat_product_basis().reshape(4, 16)
    mats = per_slot("drift_quat_products", (conj @ basis).reshape(-1, 4, 4))  # [S, 4, 4]
    quat_d = g.op("Squeeze", [g.op("MatMul", [g.op("Unsqueeze", [quat, one]), mats]), one])
    return rot_d, centers_d, quat_d


def _frame_index(g: GraphBuilder, x: str, signatures: np.ndarray, size_hw: tuple[int, int]) -> str:
    """Nodes giving ``[S]`` int64: the stored frame whose signature is nearest each input frame's."""
    hn, wn = size_hw
    grid = SIGNATURE_GRID
    pooled = g.op("AveragePool", [x], kernel_shape=[hn // grid, wn // grid], strides=[hn // grid, wn // grid])
    sig = g.op("Flatten", [pooled], axis=1)  # [S, 3 * 8 * 8]
    stored = signatures.astype(np.float32)
    # Squared distance up to the per-row constant |sig|^2: |stored|^2 - 2 sig . stored.
    dist = g.op("Add", [g.op("MatMul", [sig, g.const(-2.0 * stored.T)]), g.const((stored**2).sum(1))])
    return g.op("ArgMin", [dist], axis=1, keepdims=0)


def _quat_relative_to_first(g: GraphBuilder, quat: str, quat0: str) -> str:
    """Nodes giving ``[S, 4]`` xyzw: each frame's rotation relative to the first frame's."""
    # q_rel = q_i (x) conj(q_0) = q_i @ M(conj(q_0)), M linear in its argument.
    quat0_conj = g.op("Mul", [quat0, g.const(np.array([-1, -1, -1, 1], np.float32))])
    basis = quat_product_basis().reshape(4, 16).astype(np.float32)
    mat = g.op(
        "Reshape",
        [
            g.op("MatMul", [g.op("Unsqueeze", [quat0_conj, g.const(np.array([0], np.int64))]), g.const(basis)]),
            g.const(np.array([4, 4], np.int64)),
        ],
    )
    return g.op("MatMul", [quat, mat])


def _points_in_first_camera(
    g: GraphBuilder,
    rot: str,
    rot0: str,
    diff: str,
    depth: str,
    inv_f: str,
    last: str,
    size_hw: tuple[int, int],
) -> str:
    """Nodes giving ``[S, P, 3]``: each frame's unprojected depth in the first frame's camera.

    ``diff`` is ``c_0 - c_i`` ``[S, 3]``, ``inv_f`` the inverse focal lengths ``[S, 2]``, ``last`` the
    constant ``[-1]``; pixel rays follow the COLMAP pixel-centre rule about the image centre.
    """
    hn, wn = size_hw
    # Points: p_rel = p_cam @ (R_i R_0^T) - (c_0 - c_i) @ R_0^T, rows are points.
    rot0_t = g.op("Transpose", [rot0], perm=[1, 0])
    to_first = g.op("MatMul", [rot, rot0_t])  # [S, 3, 3]
    offset = g.op("Neg", [g.op("MatMul", [diff, rot0_t])])  # [S, 3]
    u = (np.arange(wn) + 0.5 - wn / 2).astype(np.float32)
    v = (np.arange(hn) + 0.5 - hn / 2).astype(np.float32)
    u_grid = g.const(np.tile(u, hn)[None], "u_minus_cx")  # [1, P]
    v_grid = g.const(np.repeat(v, wn)[None], "v_minus_cy")
    split = g.op("Split", [inv_f], axis=1, n_out=2)
    ray_x, ray_y = g.op("Mul", [u_grid, split[0]]), g.op("Mul", [v_grid, split[1]])
    comps = [g.op("Unsqueeze", [g.op("Mul", [r, depth]), last]) for r in (ray_x, ray_y)]
    p_cam = g.op("Concat", comps + [g.op("Unsqueeze", [depth, last])], axis=-1)  # [S, P, 3]
    one = g.const(np.array([1], np.int64))
    return g.op("Add", [g.op("MatMul", [p_cam, to_first]), g.op("Unsqueeze", [offset, one])])


def prediction_from_truth(
    scene: SyntheticScene | RealScene, truth: SimulatedTruth, options: SimulationOptions = SimulationOptions()
) -> Prediction:
    """What the simulated model says, at original resolution in the ground-truth world frame.

    For tests and benchmarks of later stages that should not depend on the ONNX path; the
    confidence follows the same rule as the model's (lower where the injected depth error is large).
    """
    conf = 1 + (_CONF_MAX - 1) * np.exp(-np.abs(truth.depth_error) / max(options.depth_error, 1e-6))
    cameras = tuple(PinholeCamera.from_K(K, scene.camera.width, scene.camera.height) for K in truth.K)
    model = ModelInfo(
        "simulated", ModelFamily.MULTIVIEW, simulated=True, description="simulated model outputs, no ONNX"
    )
    return Prediction(
        scene.names, truth.cam_from_world, cameras, tuple(truth.depth), tuple(conf.astype(np.float32)), model
    )
