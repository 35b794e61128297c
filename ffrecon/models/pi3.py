"""The Pi3 contract (yyfz/Pi3): reference preprocessing and decoding to a :class:`Prediction`.

A Pi3 export takes ``images [N, 3, H, W]`` float32 RGB in [0, 1] and returns ``local_points
[1, N, H, W, 3]`` (each camera's frame, OpenCV axes), ``conf [1, N, H, W, 1]`` (a logit: the
reference applies a sigmoid), ``camera_poses [1, N, 4, 4]`` (**world_from_cam**) and optionally
``points`` (world frame). Pi3 is permutation-equivariant: its world frame is no input frame.

Decoding, with upstream's own conventions:

- World frame: ffrecon takes the first frame of each call as the world,
  ``cam_from_world_i = inv(world_from_cam_i) * world_from_cam_0`` (frame 0 gets the identity).
- Intrinsics: Pi3 outputs none. Each frame's pinhole focal is upstream's
  ``pi3.utils.geometry.recover_intrinsic_from_rays_d(local_points, force_center_principal_point=True)``:
  the least-squares ``fx`` (``fy``) fitting ``u - cx = fx * x / |z|`` over every pixel with the
  principal point at the image centre (upstream's ``(W - 1) / 2`` on pixel indices is ``W / 2``
  in ffrecon's COLMAP pixel-centre rule: the same point).
- Depth: ``local_points`` z (z-depth in the camera; Pi3 makes it ``exp(.) > 0``).
- Confidence: ``depth_conf = 1 + exp(conf) = 1 / (1 - sigmoid(conf))``, the same ``1 + exp``
  activation VGGT's heads use, so ffrecon's ">= 1 where known" convention and thresholds carry
  over. The reference's mask ``sigmoid(conf) > 0.1`` is ``depth_conf > 1.11``; sigmoid 0.5 is 2.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
from PIL import Image

from ffrecon.checks import check_finite, require_outputs, strip_batch_axis
from ffrecon.errors import ModelError
from ffrecon.geometry.poses import compose_poses, invert_pose
from ffrecon.models.adapters import MultiviewAdapter, PreprocessMode
from ffrecon.models.resize import ResizeTransform, prediction_in_original_pixels
from ffrecon.types import ModelFamily, ModelInfo, Prediction

PATCH_SIZE = 14
PIXEL_LIMIT = 255_000  # load_images_as_tensor's default: the reference resolution (about 574 x 434)
INPUT_NAME = "images"
OUTPUT_NAMES = ("local_points", "conf", "camera_poses")  # required; points is optional
MAX_CONF_LOGIT = 60.0  # 1 + exp(60) ~ 1e26 still fits float32


def network_size_hw(height: int, width: int, pixel_limit: int = PIXEL_LIMIT) -> tuple[int, int]:
    """``(H, W)`` that Pi3's ``load_images_as_tensor`` resizes a ``height`` x ``width`` photo to.

    Scale to about ``pixel_limit`` pixels, round each side to a multiple of 14, then shrink the side
    that most exceeds the aspect ratio until the area fits (upstream's loop, Python rounding).

    >>> network_size_hw(480, 640), network_size_hw(640, 480), network_size_hw(1080, 1920)
    ((434, 574), (574, 434), (378, 672))
    """
    if height <= 0 or width <= 0:
        raise ModelError(f"cannot preprocess an image of {width}x{height} pixels", "pass non-empty images")
    scale = math.sqrt(pixel_limit / (width * height))
    w_target, h_target = width * scale, height * scale
    k, m = round(w_target / PATCH_SIZE), round(h_target / PATCH_SIZE)
    while (k * PATCH_SIZE) * (m * PATCH_SIZE) > pixel_limit:
        if k / m > w_target / h_target:
            k -= 1
        else:
            m -= 1
    return max(1, m) * PATCH_SIZE, max(1, k) * PATCH_SIZE


def preprocess_pi3(
    images: Sequence[np.ndarray], mode: PreprocessMode = PreprocessMode.CROP
) -> tuple[np.ndarray, tuple[ResizeTransform, ...]]:
    """Pi3's reference preprocessing (``pi3.utils.basic.load_images_as_tensor``) with its bookkeeping.

    Every image is resized (PIL Lanczos, no crop, no padding) to the size the *first* image gets
    from :func:`network_size_hw`, then scaled to [0, 1] as torchvision's ``ToTensor`` does.

    Args:
        images: N images ``[H, W, 3]`` uint8 RGB (sizes may differ; later ones are resized to the
            first one's network size, as upstream does, so their scale may differ per axis).
        mode: only ``CROP`` (the label of each family's reference preprocessing).
    Returns:
        ``([N, 3, H, W] float32 RGB in [0, 1], N transforms original -> network)``.
    """
    if mode is not PreprocessMode.CROP:
        raise ModelError(f"Pi3 has no '{mode.value}' preprocessing", "use --preprocess crop (Pi3's reference resize)")
    if not images:
        raise ModelError("no images to preprocess", "pass at least one image")
    h0, w0 = images[0].shape[:2]
    size_hw = network_size_hw(h0, w0)
    batch, transforms = [], []
    for image in images:
        h, w = image.shape[:2]
        resized = Image.fromarray(image).resize((size_hw[1], size_hw[0]), Image.Resampling.LANCZOS)
        batch.append(np.asarray(resized, dtype=np.float32) / np.float32(255.0))
        transforms.append(ResizeTransform((w, h), (size_hw[1], size_hw[0]), size_hw[1] / w, size_hw[0] / h))
    return np.ascontiguousarray(np.stack(batch).transpose(0, 3, 1, 2)), tuple(transforms)


def focal_from_local_points(local_points: np.ndarray) -> np.ndarray:
    """Per-frame ``(fx, fy)`` in network pixels, principal point at the image centre.

    Upstream's ``recover_intrinsic_from_rays_d(..., force_center_principal_point=True)`` in float64:
    ``fx = sum(x_proj * (u - cx)) / sum(x_proj^2)`` with ``x_proj = x / (|z| + 1e-10)`` over all pixels.

    Args:
        local_points: ``[N, H, W, 3]`` points in each camera's frame (any scale).
    Returns:
        ``[N, 2]`` float64.
    """
    pts = np.asarray(local_points, dtype=np.float64)
    _, h, w, _ = pts.shape
    z = np.abs(pts[..., 2]) + 1e-10
    x, y = pts[..., 0] / z, pts[..., 1] / z
    du = np.arange(w) - (w - 1) / 2.0  # pixel-index offsets from the centre (COLMAP: u + 0.5 - W / 2, the same)
    dv = np.arange(h) - (h - 1) / 2.0
    with np.errstate(divide="ignore", invalid="ignore"):
        fx = (x * du[None, None, :]).sum(axis=(1, 2)) / (x * x).sum(axis=(1, 2))
        fy = (y * dv[None, :, None]).sum(axis=(1, 2)) / (y * y).sum(axis=(1, 2))
    return np.stack([fx, fy], axis=-1)


def depth_conf_from_logit(logit: np.ndarray) -> np.ndarray:
    """``1 + exp(logit)`` = ``1 / (1 - sigmoid(logit))``: >= 1, monotone in Pi3's confidence.

    >>> depth_conf_from_logit(np.array([0.0, np.log(1 / 9)], np.float32)).round(4)
    array([2.    , 1.1111], dtype=float32)
    """
    return (1.0 + np.exp(np.minimum(np.asarray(logit, dtype=np.float64), MAX_CONF_LOGIT))).astype(np.float32)


def _without_batch(name: str, array: np.ndarray, shape: tuple[int | None, ...]) -> np.ndarray:
    return strip_batch_axis(name, array, shape, fix="export the model with `ffrecon export-model pi3` (docs/models.md)")


def decode_pi3_outputs(
    outputs: Mapping[str, np.ndarray],
    transforms: Sequence[ResizeTransform],
    names: Sequence[str],
    model: ModelInfo,
    *,
    max_depth_side: int | None = None,
) -> Prediction:
    """Pi3 outputs for N frames to a :class:`Prediction` in original-photo pixels.

    Args:
        outputs: ``local_points [1, N, H, W, 3]``, ``conf [1, N, H, W, 1]``, ``camera_poses
            [1, N, 4, 4]`` world_from_cam (the batch axis and conf's last axis are optional).
        transforms: the N transforms returned by :func:`preprocess_pi3`.
        names: N frame names.
        max_depth_side: cap on the long side of the returned depth grids (None: original size).
    Returns:
        cam_from_world with frame 0 as the world; K, depth (local z) and ``1 + exp(conf)`` per frame.
    """
    require_outputs(
        outputs,
        OUTPUT_NAMES,
        fix="a Pi3-contract model must output local_points, conf and camera_poses (docs/models.md)",
    )
    n = len(transforms)
    wn, hn = transforms[0].net_size_wh
    local_points = _without_batch("local_points", outputs["local_points"], (n, hn, wn, 3))
    conf = np.asarray(outputs["conf"])
    conf = _without_batch("conf", conf[..., 0] if conf.ndim >= 4 and conf.shape[-1] == 1 else conf, (n, hn, wn))
    world_from_cam = _without_batch("camera_poses", outputs["camera_poses"], (n, 4, 4))
    for key, value in (("local_points", local_points), ("conf", conf), ("camera_poses", world_from_cam)):
        check_finite(key, value, model=model.path)
    world_from_cam = world_from_cam[:, :3, :4].astype(np.float64)
    cam_from_world = compose_poses(invert_pose(world_from_cam), world_from_cam[0])  # frame 0 is the world
    focal = focal_from_local_points(local_points)
    depth = local_points[..., 2].astype(np.float32)
    depth_conf = np.where(depth > 0, depth_conf_from_logit(conf), np.float32(0.0))
    depth = np.maximum(depth, np.float32(0.0))
    K_net = np.zeros((len(transforms), 3, 3))
    K_net[:, 0, 0], K_net[:, 1, 1] = focal[:, 0], focal[:, 1]
    K_net[:, 0, 2], K_net[:, 1, 2], K_net[:, 2, 2] = wn / 2, hn / 2, 1.0
    return prediction_in_original_pixels(
        names, cam_from_world, K_net, depth, depth_conf, transforms, model, max_depth_side=max_depth_side
    )


ADAPTER = MultiviewAdapter(
    family=ModelFamily.PI3,
    input_name=INPUT_NAME,
    output_names=OUTPUT_NAMES,
    preprocess=lambda images, mode: preprocess_pi3(images, mode),
    decode=lambda outputs, transforms, names, model, max_side: decode_pi3_outputs(
        outputs, transforms, names, model, max_depth_side=max_side
    ),
    modes=(PreprocessMode.CROP,),
    world_frame="the first frame of each model call "
    "(Pi3 has no reference frame; its world_from_cam poses are re-expressed relative to frame 0)",
    camera_outputs="camera_poses (poses) and local_points (focal, fitted as upstream's recover_intrinsic_from_rays_d)",
    description="Pi3 contract: local_points (camera frame), conf (logit; depth_conf = 1 + exp), "
    "camera_poses (world_from_cam)",
)
