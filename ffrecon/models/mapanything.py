"""The MapAnything contract (facebookresearch/map-anything): reference preprocessing and decoding.

MapAnything returns one dict per view; ffrecon's ONNX contract stacks them over the S views with a
leading batch axis of 1 (names as upstream's ``model.infer`` outputs):

| name | shape | meaning |
| --- | --- | --- |
| input ``images`` | ``[S, 3, H, W]`` float32 RGB in [0, 1] | the export applies DINOv2's mean/std itself |
| ``ray_directions`` | ``[1, S, H, W, 3]`` | unit ray per pixel, camera frame (OpenCV axes) |
| ``depth_along_ray`` | ``[1, S, H, W, 1]`` | distance along the ray (metric: scaling already applied) |
| ``cam_trans`` | ``[1, S, 3]`` | **world_from_cam** translation (metric) |
| ``cam_quats`` | ``[1, S, 4]`` | **world_from_cam** rotation, quaternion **xyzw** (scalar last) |
| ``conf`` | ``[1, S, H, W]`` | confidence, ``1 + exp(.)`` (upstream's ``confidence_type: exp``, ``vmin: 1``) |
| optional ``pts3d``, ``pts3d_cam`` | ``[1, S, H, W, 3]`` | world / camera points (not needed to decode) |
| optional ``metric_scaling_factor`` | ``[1, S]`` or ``[1]`` | the scale already applied to the metric outputs |

``cam_quats`` is read the way upstream's ``quaternion_to_rotation_matrix`` reads it (xyzw).

H and W come from MapAnything's ``load_images`` (``resize_mode="fixed_mapping"``, resolution set
518): the aspect ratio closest to the call's mean aspect picks a size from a fixed table (4:3 ->
518 x 392); each image is scaled to cover it (PIL Lanczos when shrinking, bicubic when enlarging,
new size ``floor(side * s)``) and centre-cropped.

Decoding:

- World frame: MapAnything predicts poses in its reference view 0's frame; ffrecon makes frame 0
  exactly the world: ``cam_from_world_i = inv(world_from_cam_i) * world_from_cam_0``.
- Intrinsics: upstream's ``recover_pinhole_intrinsics_from_ray_directions`` (standard-resolution
  branch): a least-squares line ``u = cx + fx * dx / dz`` (and ``v``) over every ``H // 50``-th row
  and ``W // 50``-th column, principal point free. Its pixel index ``u`` is ffrecon's ``u + 0.5``.
- Depth: z-depth ``depth_along_ray * dz / |d|``.
- Confidence: ``conf`` as it is (already >= 1, ffrecon's convention).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
from PIL import Image

from ffrecon.checks import check_finite, require_outputs, strip_batch_axis
from ffrecon.errors import ModelError
from ffrecon.geometry.poses import compose_poses, invert_pose
from ffrecon.geometry.rotations import quat_xyzw_to_matrix
from ffrecon.models.adapters import MultiviewAdapter, PreprocessMode
from ffrecon.models.resize import ResizeTransform, prediction_in_original_pixels
from ffrecon.types import ModelFamily, ModelInfo, Prediction

PATCH_SIZE = 14
INPUT_NAME = "images"
OUTPUT_NAMES = ("ray_directions", "depth_along_ray", "cam_trans", "cam_quats", "conf")  # required
OPTIONAL_OUTPUTS = ("pts3d", "pts3d_cam", "metric_scaling_factor")
# mapanything.utils.image.RESOLUTION_MAPPINGS[518]: aspect ratio (W / H) -> (width, height)
RESOLUTION_518 = {
    1.000: (518, 518),
    1.321: (518, 392),
    1.542: (518, 336),
    1.762: (518, 294),
    2.056: (518, 252),
    3.083: (518, 168),
    0.757: (392, 518),
    0.649: (336, 518),
    0.567: (294, 518),
    0.486: (252, 518),
}
INTRINSICS_SAMPLES = 50  # upstream samples every (side // 50)-th row and column for the focal fit


def network_size_hw(aspect_ratios: Sequence[float]) -> tuple[int, int]:
    """``(H, W)`` for a call whose images have these width / height ratios (their mean picks the size).

    >>> network_size_hw([640 / 480]), network_size_hw([480 / 640]), network_size_hw([1920 / 1080])
    ((392, 518), (518, 392), (294, 518))
    """
    mean = sum(aspect_ratios) / len(aspect_ratios)
    key = min(sorted(RESOLUTION_518), key=lambda k: abs(k - mean))  # upstream's search order (ties: the smaller)
    width, height = RESOLUTION_518[key]
    return height, width


def preprocess_mapanything(
    images: Sequence[np.ndarray], mode: PreprocessMode = PreprocessMode.CROP
) -> tuple[np.ndarray, tuple[ResizeTransform, ...]]:
    """MapAnything's ``load_images(resize_mode="fixed_mapping")`` with the bookkeeping to undo it.

    Args:
        images: S images ``[H, W, 3]`` uint8 RGB (sizes may differ: all go to one network size).
        mode: only ``CROP`` (fixed mapping: cover the table size, then centre-crop).
    Returns:
        ``([S, 3, Hn, Wn] float32 RGB in [0, 1], S transforms original -> network)``; the DINOv2
        normalisation is part of the exported model.
    """
    if mode is not PreprocessMode.CROP:
        raise ModelError(
            f"MapAnything has no '{mode.value}' preprocessing",
            "use --preprocess crop (MapAnything's fixed-mapping resize and centre crop)",
        )
    if not images:
        raise ModelError("no images to preprocess", "pass at least one image")
    hn, wn = network_size_hw([im.shape[1] / im.shape[0] for im in images])
    batch, transforms = [], []
    for image in images:
        h, w = image.shape[:2]
        scale = max(wn / w, hn / h) + 1e-8  # upstream's rescale_image_and_other_optional_info
        new_w, new_h = math.floor(w * scale), math.floor(h * scale)
        resample = Image.Resampling.LANCZOS if scale < 1 else Image.Resampling.BICUBIC
        resized = np.asarray(Image.fromarray(image).resize((new_w, new_h), resample), dtype=np.float32) / np.float32(
            255.0
        )
        left, top = (new_w - wn) // 2, (new_h - hn) // 2
        batch.append(resized[top : top + hn, left : left + wn])
        transforms.append(ResizeTransform((w, h), (wn, hn), new_w / w, new_h / h, -float(left), -float(top)))
    return np.ascontiguousarray(np.stack(batch).transpose(0, 3, 1, 2)), tuple(transforms)


def intrinsics_from_rays(ray_directions: np.ndarray) -> np.ndarray:
    """Per-view ``K [S, 3, 3]`` in network pixels (COLMAP pixel-centre rule) from ray directions.

    Upstream's least-squares fit ``u = cx + fx * dx / dz`` over its sampled pixel grid, in float64;
    upstream's pixel index u is pixel u's centre, ``u + 0.5`` here, so ``cx = cx_upstream + 0.5``.

    Args:
        ray_directions: ``[S, H, W, 3]`` rays in each camera's frame (any length).
    """
    rays = np.asarray(ray_directions, dtype=np.float64)
    _, h, w, _ = rays.shape
    rows = np.arange(0, h, max(1, h // INTRINSICS_SAMPLES))
    cols = np.arange(0, w, max(1, w // INTRINSICS_SAMPLES))
    sampled = rays[:, rows[:, None], cols[None, :]]  # [S, h', w', 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio_x = (sampled[..., 0] / sampled[..., 2]).reshape(len(rays), -1)
        ratio_y = (sampled[..., 1] / sampled[..., 2]).reshape(len(rays), -1)
        u = np.broadcast_to(cols[None, :] + 0.5, sampled.shape[1:3]).reshape(-1)
        v = np.broadcast_to(rows[:, None] + 0.5, sampled.shape[1:3]).reshape(-1)
        fx, cx = _line_fit(ratio_x, u)
        fy, cy = _line_fit(ratio_y, v)
    K = np.zeros((len(rays), 3, 3))
    K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = fx, fy, cx, cy, 1.0
    return K


def _line_fit(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per row of ``x [S, N]``: slope and intercept of the least-squares line ``y = b + a x``."""
    xc = x - x.mean(axis=1, keepdims=True)
    slope = (xc * (y[None, :] - y.mean())).sum(axis=1) / (xc * xc).sum(axis=1)
    return slope, y.mean() - slope * x.mean(axis=1)


def _without_batch(name: str, array: np.ndarray, shape: tuple[int | None, ...]) -> np.ndarray:
    return strip_batch_axis(
        name,
        array,
        shape,
        fix="export the model with ffrecon's MapAnything contract (docs/models.md): "
        "per-view outputs stacked over views",
    )


def decode_mapanything_outputs(
    outputs: Mapping[str, np.ndarray],
    transforms: Sequence[ResizeTransform],
    names: Sequence[str],
    model: ModelInfo,
    *,
    max_depth_side: int | None = None,
) -> Prediction:
    """MapAnything outputs for S views to a :class:`Prediction` in original-photo pixels.

    Args:
        outputs: the contract's outputs (table in the module docstring; the batch axis and
            depth_along_ray's last axis are optional).
        transforms: the S transforms returned by :func:`preprocess_mapanything`.
        names: S frame names.
        max_depth_side: cap on the long side of the returned depth grids (None: original size).
    Returns:
        cam_from_world with frame 0 as the world; K from the rays, z-depth and conf per frame.
    """
    require_outputs(
        outputs,
        OUTPUT_NAMES,
        fix=f"a MapAnything-contract model must output {', '.join(OUTPUT_NAMES)} (docs/models.md)",
    )
    s = len(transforms)
    wn, hn = transforms[0].net_size_wh
    rays = _without_batch("ray_directions", outputs["ray_directions"], (s, hn, wn, 3))
    dist = np.asarray(outputs["depth_along_ray"])
    dist = _without_batch(
        "depth_along_ray", dist[..., 0] if dist.ndim >= 4 and dist.shape[-1] == 1 else dist, (s, hn, wn)
    )
    trans = _without_batch("cam_trans", outputs["cam_trans"], (s, 3))
    quats = _without_batch("cam_quats", outputs["cam_quats"], (s, 4))
    conf = np.asarray(outputs["conf"])
    conf = _without_batch("conf", conf[..., 0] if conf.ndim >= 4 and conf.shape[-1] == 1 else conf, (s, hn, wn))
    for key, value in (
        ("ray_directions", rays),
        ("depth_along_ray", dist),
        ("cam_trans", trans),
        ("cam_quats", quats),
        ("conf", conf),
    ):
        check_finite(key, value, model=model.path)
    norms = np.linalg.norm(quats.astype(np.float64), axis=-1)
    if not (norms > 1e-6).all():
        raise ModelError(
            f"model output 'cam_quats' has a zero quaternion for {int((norms <= 1e-6).sum())} of {s} views",
            "the export is broken or the model untrained: re-export it from a trained checkpoint",
        )
    world_from_cam = np.concatenate([quat_xyzw_to_matrix(quats), trans.astype(np.float64)[:, :, None]], axis=2)
    cam_from_world = compose_poses(invert_pose(world_from_cam), world_from_cam[0])  # frame 0 is the world
    K_net = intrinsics_from_rays(rays)
    length = np.linalg.norm(rays.astype(np.float64), axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.where(length > 0, dist * rays[..., 2] / length, 0.0).astype(np.float32)
    depth_conf = np.where(depth > 0, conf, 0.0).astype(np.float32)
    depth = np.maximum(depth, np.float32(0.0))
    return prediction_in_original_pixels(
        names, cam_from_world, K_net, depth, depth_conf, transforms, model, max_depth_side=max_depth_side
    )


ADAPTER = MultiviewAdapter(
    family=ModelFamily.MAPANYTHING,
    input_name=INPUT_NAME,
    output_names=OUTPUT_NAMES,
    preprocess=lambda images, mode: preprocess_mapanything(images, mode),
    decode=lambda outputs, transforms, names, model, max_side: decode_mapanything_outputs(
        outputs, transforms, names, model, max_depth_side=max_side
    ),
    modes=(PreprocessMode.CROP,),
    world_frame="the first frame of each model call "
    "(MapAnything's reference view 0; its world_from_cam poses are re-expressed relative to it)",
    camera_outputs="cam_trans/cam_quats (poses) and ray_directions (intrinsics)",
    description="MapAnything contract: ray_directions, depth_along_ray, "
    "cam_trans/cam_quats (world_from_cam, xyzw), conf",
)
