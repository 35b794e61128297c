"""The VGGT contract (docs/contracts.md, "Multi-view models"): preprocessing, pose encoding, decoding.

All functions work on plain numpy arrays; :mod:`ffrecon.models.multiview` runs them around a model.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from PIL import Image

from ffrecon.checks import check_finite, require_outputs, strip_batch_axis
from ffrecon.errors import ModelError
from ffrecon.geometry.rotations import matrix_to_quat_xyzw, quat_xyzw_to_matrix
from ffrecon.models.adapters import MultiviewAdapter, PreprocessMode
from ffrecon.models.resize import ResizeTransform, prediction_in_original_pixels
from ffrecon.types import ModelFamily, ModelInfo, Prediction

PATCH_SIZE = 14
TARGET_SIZE = 518
INPUT_NAME = "input_images"
OUTPUT_NAMES = ("pose_enc", "depth", "depth_conf")  # required; world_points etc. are optional


def _round14(x: float) -> int:
    return int(round(x / PATCH_SIZE)) * PATCH_SIZE


def network_size_hw(
    height: int, width: int, mode: PreprocessMode = PreprocessMode.CROP, target_size: int = TARGET_SIZE
) -> tuple[int, int]:
    """Network input ``(H, W)`` that :func:`preprocess_vggt` gives a ``height`` x ``width`` photo.

    >>> network_size_hw(480, 640), network_size_hw(640, 480), network_size_hw(480, 640, PreprocessMode.PAD)
    ((392, 518), (518, 518), (518, 518))
    """
    if mode is PreprocessMode.PAD:
        return (target_size, target_size)
    return (min(_round14(height * target_size / width), target_size), target_size)


def preprocess_vggt(
    images: Sequence[np.ndarray], mode: PreprocessMode = PreprocessMode.CROP, target_size: int = TARGET_SIZE
) -> tuple[np.ndarray, tuple[ResizeTransform, ...]]:
    """The reference preprocessing, with the coordinate bookkeeping to undo it.

    Args:
        images: S images ``[H, W, 3]`` uint8 RGB (sizes may differ).
        mode: CROP (reference default) or PAD.
    Returns:
        ``([S, 3, Hn, Wn] float32 RGB in [0, 1], S transforms original -> network)``.
        Images of different network sizes are padded with white to the largest, centred, as the
        reference code does.
    """
    if mode not in (PreprocessMode.CROP, PreprocessMode.PAD):
        raise ModelError(
            f"VGGT has no '{mode.value}' preprocessing", "use --preprocess crop (the reference default) or pad"
        )
    resized: list[np.ndarray] = []
    transforms: list[ResizeTransform] = []
    for image in images:
        h, w = image.shape[:2]
        if mode is PreprocessMode.CROP:
            new_w, new_h = target_size, _round14(h * target_size / w)
        elif w >= h:
            new_w, new_h = target_size, _round14(h * target_size / w)
        else:
            new_w, new_h = _round14(w * target_size / h), target_size
        # PIL bicubic, as the reference does (through torchvision's ToTensor afterwards).
        arr = (
            np.asarray(Image.fromarray(image).resize((new_w, new_h), Image.Resampling.BICUBIC), dtype=np.float32)
            / 255.0
        )
        off_x = off_y = 0.0
        if mode is PreprocessMode.CROP and new_h > target_size:
            start = (new_h - target_size) // 2
            arr = arr[start : start + target_size]
            off_y = -float(start)
        elif mode is PreprocessMode.PAD:
            pad_t, pad_l = (target_size - new_h) // 2, (target_size - new_w) // 2
            arr = _pad_white(arr, target_size, target_size, pad_t, pad_l)
            off_x, off_y = float(pad_l), float(pad_t)
        resized.append(arr)
        transforms.append(ResizeTransform((w, h), (arr.shape[1], arr.shape[0]), new_w / w, new_h / h, off_x, off_y))
    max_h = max(a.shape[0] for a in resized)
    max_w = max(a.shape[1] for a in resized)
    for k, arr in enumerate(resized):
        if arr.shape[:2] != (max_h, max_w):
            pad_t, pad_l = (max_h - arr.shape[0]) // 2, (max_w - arr.shape[1]) // 2
            resized[k] = _pad_white(arr, max_h, max_w, pad_t, pad_l)
            t = transforms[k]
            transforms[k] = ResizeTransform(
                t.orig_size_wh, (max_w, max_h), t.scale_x, t.scale_y, t.offset_x + pad_l, t.offset_y + pad_t
            )
    batch = np.stack(resized).transpose(0, 3, 1, 2)
    return np.ascontiguousarray(batch, dtype=np.float32), tuple(transforms)


def _pad_white(arr: np.ndarray, height: int, width: int, top: int, left: int) -> np.ndarray:
    out = np.ones((height, width, arr.shape[2]), np.float32)
    out[top : top + arr.shape[0], left : left + arr.shape[1]] = arr
    return out


def decode_pose_enc(pose_enc: np.ndarray, size_hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``[S, 9]`` (t, quat_xyzw, fov_h, fov_w) to ``([S, 3, 4] cam_from_world, [S, 3, 3] K)``.

    K is in network pixels with the principal point at the image centre (COLMAP rule: W/2, H/2).
    """
    enc = np.asarray(pose_enc, dtype=np.float64)
    h, w = size_hw
    rot = quat_xyzw_to_matrix(enc[:, 3:7])
    cam_from_world = np.concatenate([rot, enc[:, :3, None]], axis=2)
    K = np.zeros((len(enc), 3, 3))
    with np.errstate(divide="ignore"):  # fov 0 gives an infinite focal: validate_prediction reports it
        K[:, 0, 0] = (w / 2) / np.tan(enc[:, 8] / 2)
        K[:, 1, 1] = (h / 2) / np.tan(enc[:, 7] / 2)
    K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = w / 2, h / 2, 1.0
    return cam_from_world, K


def encode_pose_enc(cam_from_world: np.ndarray, K: np.ndarray, size_hw: tuple[int, int]) -> np.ndarray:
    """Inverse of :func:`decode_pose_enc` (the principal point is not encoded)."""
    h, w = size_hw
    quat = matrix_to_quat_xyzw(cam_from_world[:, :3, :3])
    fov_h = 2 * np.arctan((h / 2) / K[:, 1, 1])
    fov_w = 2 * np.arctan((w / 2) / K[:, 0, 0])
    return np.concatenate([cam_from_world[:, :3, 3], quat, fov_h[:, None], fov_w[:, None]], axis=1)


def _squeeze_batch(name: str, array: np.ndarray, rank_without_batch: int) -> np.ndarray:
    """Accept outputs with or without the leading batch axis of size 1."""
    return strip_batch_axis(
        name,
        array,
        (None,) * rank_without_batch,
        fix="export the model with the VGGT output contract (`ffrecon export-model vggt`; docs/models.md)",
    )


def decode_vggt_outputs(
    outputs: Mapping[str, np.ndarray],
    transforms: Sequence[ResizeTransform],
    names: Sequence[str],
    model: ModelInfo,
    *,
    max_depth_side: int | None = None,
) -> Prediction:
    """VGGT outputs for S frames to a :class:`Prediction` in original-photo pixels.

    Args:
        outputs: at least ``pose_enc [1, S, 9]``, ``depth [1, S, H, W, 1]``, ``depth_conf [1, S, H, W]``
            (the leading batch axis and the trailing depth axis are optional).
        transforms: the S transforms returned by :func:`preprocess_vggt`.
        names: S frame names.
        max_depth_side: cap on the long side of the returned depth grids (None: original size).
    """
    require_outputs(
        outputs,
        OUTPUT_NAMES,
        fix="a VGGT-contract model must output pose_enc, depth and depth_conf (docs/contracts.md, 'Multi-view models')",
    )
    for key in OUTPUT_NAMES:
        check_finite(key, np.asarray(outputs[key]), model=model.path)
    pose_enc = _squeeze_batch("pose_enc", np.asarray(outputs["pose_enc"]), 2)
    depth = np.asarray(outputs["depth"])
    depth = _squeeze_batch("depth", depth[..., 0] if depth.shape[-1] == 1 and depth.ndim >= 4 else depth, 3)
    conf = _squeeze_batch("depth_conf", np.asarray(outputs["depth_conf"]), 3)
    s = len(transforms)
    if pose_enc.shape != (s, 9) or depth.shape[0] != s or conf.shape != depth.shape:
        raise ModelError(
            f"model outputs disagree with the {s} input frames: pose_enc {pose_enc.shape}, depth {depth.shape}, "
            f"depth_conf {conf.shape}",
            "check that the model follows the VGGT contract",
        )
    size_hw = depth.shape[1:3]
    cam_from_world, K_net = decode_pose_enc(pose_enc, size_hw)
    return prediction_in_original_pixels(
        names, cam_from_world, K_net, depth, conf, transforms, model, max_depth_side=max_depth_side
    )


ADAPTER = MultiviewAdapter(
    family=ModelFamily.MULTIVIEW,
    input_name=INPUT_NAME,
    output_names=OUTPUT_NAMES,
    preprocess=lambda images, mode: preprocess_vggt(images, mode),
    decode=lambda outputs, transforms, names, model, max_side: decode_vggt_outputs(
        outputs, transforms, names, model, max_depth_side=max_side
    ),
    modes=(PreprocessMode.CROP, PreprocessMode.PAD),
    world_frame="the first frame's camera (VGGT's convention)",
    camera_outputs="pose_enc",
    description="VGGT contract: pose_enc (t, quat_xyzw, fov_h, fov_w), depth, depth_conf",
)
