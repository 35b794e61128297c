"""The Depth Anything 3 contract: DA3's reference preprocessing and the decoding of its outputs.

A ``da3`` ONNX file (``ffrecon export-model da3``) takes ``images [S, 3, H, W]`` float32 RGB in
[0, 1] and returns ``depth``, ``depth_conf`` ``[1, S, H, W]``, ``extrinsics [1, S, 3, 4]`` (OpenCV
cam_from_world, relative to the reference view DA3 picks) and ``intrinsics [1, S, 3, 3]`` (network
pixels, principal point at the image centre). The functions work on numpy arrays;
:mod:`ffrecon.models.multiview` runs them around a model.

Preprocessing follows ``depth_anything_3.utils.io.input_processor.InputProcessor`` (504 px):

1. boundary resize: the longest side (``upper_bound_*``) or the shortest side (``lower_bound_*``)
   to 504, sides ``round(side * scale)``, OpenCV ``INTER_CUBIC`` when enlarging, else ``INTER_AREA``;
2. sides to multiples of 14: ``*_resize`` rounds each side to the nearest multiple (ties upward)
   with a second resize (cubic if either side grows, else area); ``*_crop`` floors each side by a
   centre crop (offsets ``(w - w14) // 2``);
3. frames of different sizes are centre-cropped to the smallest height and width (torchvision's
   ``CenterCrop`` offsets, ``round((H - h) / 2)``);
4. ``[0, 1]`` RGB (the ONNX file applies the ImageNet normalisation itself).

Decoding: the world frame becomes the first frame's camera (DA3's extrinsics are relative to the
view it selected as reference, which is not always frame 0); ``depth_conf`` is DA3's
``1 + exp(logit)`` ("expp1"), already ffrecon's ``>= 1`` scale, and is used as it is.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import cv2
import numpy as np

from ffrecon.checks import check_finite, require_outputs, strip_batch_axis
from ffrecon.errors import InputError, ModelError
from ffrecon.geometry.poses import compose_poses, invert_pose
from ffrecon.models.adapters import MultiviewAdapter, PreprocessMode
from ffrecon.models.resize import ResizeTransform, prediction_in_original_pixels
from ffrecon.types import ModelFamily, ModelInfo, Prediction

PATCH_SIZE = 14
PROCESS_RES = 504
INPUT_NAME = "images"
OUTPUT_NAMES = ("depth", "depth_conf", "extrinsics", "intrinsics")
METHODS = ("upper_bound_resize", "upper_bound_crop", "lower_bound_resize", "lower_bound_crop")
DEFAULT_METHOD = "upper_bound_resize"  # api.DepthAnything3.inference's default

# ffrecon's preprocessing modes -> DA3's process_res_method. CROP is DA3's crop variant of the
# reference; with a RESIZE member (see the lead's notes) the reference default comes first.
MODE_METHODS: dict[PreprocessMode, str] = {PreprocessMode.CROP: "upper_bound_crop"}
if hasattr(PreprocessMode, "RESIZE"):
    MODE_METHODS = {PreprocessMode.RESIZE: DEFAULT_METHOD, **MODE_METHODS}


def _boundary_size(height: int, width: int, method: str, process_res: int) -> tuple[int, int]:
    side = max(height, width) if method.startswith("upper") else min(height, width)
    if side == process_res:
        return height, width
    scale = process_res / float(side)
    return max(1, int(round(height * scale))), max(1, int(round(width * scale)))


def _nearest_multiple(x: int, p: int = PATCH_SIZE) -> int:
    down = (x // p) * p
    up = down + p
    return up if abs(up - x) <= abs(x - down) else down


def _divisible_size(height: int, width: int, method: str) -> tuple[int, int]:
    if method.endswith("resize"):
        return max(1, _nearest_multiple(height)), max(1, _nearest_multiple(width))
    return (height // PATCH_SIZE) * PATCH_SIZE, (width // PATCH_SIZE) * PATCH_SIZE


def _check_method(method: str) -> None:
    if method not in METHODS:
        raise InputError(f"unknown Depth Anything 3 processing method '{method}'", f"use one of: {', '.join(METHODS)}")


def network_size_hw(
    height: int, width: int, method: str = DEFAULT_METHOD, process_res: int = PROCESS_RES
) -> tuple[int, int]:
    """Network input ``(H, W)`` DA3's processing gives one ``height`` x ``width`` photo.

    >>> network_size_hw(480, 640), network_size_hw(700, 1000), network_size_hw(700, 1000, "upper_bound_crop")
    ((378, 504), (350, 504), (350, 504))
    >>> network_size_hw(480, 640, "lower_bound_resize")
    (504, 672)
    """
    _check_method(method)
    return _divisible_size(*_boundary_size(height, width, method, process_res), method)


def _resize(image: np.ndarray, height: int, width: int, enlarge: bool) -> np.ndarray:
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_CUBIC if enlarge else cv2.INTER_AREA)


def preprocess_da3(
    images: Sequence[np.ndarray], method: str = DEFAULT_METHOD, process_res: int = PROCESS_RES
) -> tuple[np.ndarray, tuple[ResizeTransform, ...]]:
    """DA3's reference preprocessing (module docstring), with the bookkeeping to undo it.

    Args:
        images: S images ``[H, W, 3]`` uint8 RGB (sizes may differ).
        method: one of :data:`METHODS`.
    Returns:
        ``([S, 3, Hn, Wn] float32 RGB in [0, 1], S transforms original -> network)``.
    """
    _check_method(method)
    arrays: list[np.ndarray] = []
    transforms: list[ResizeTransform] = []
    for image in images:
        h, w = image.shape[:2]
        bh, bw = _boundary_size(h, w, method, process_res)
        side = max(h, w) if method.startswith("upper") else min(h, w)
        arr = image if side == process_res else _resize(image, bh, bw, enlarge=process_res > side)
        nh, nw = _divisible_size(bh, bw, method)
        off_x = off_y = 0.0
        if method.endswith("resize") and (nh, nw) != (bh, bw):
            arr = _resize(arr, nh, nw, enlarge=nw > bw or nh > bh)
        elif method.endswith("crop") and (nh, nw) != (bh, bw):
            left, top = (bw - nw) // 2, (bh - nh) // 2
            arr = arr[top : top + nh, left : left + nw]
            off_x, off_y = -float(left), -float(top)
        scaled_w, scaled_h = (nw, nh) if method.endswith("resize") else (bw, bh)  # size before any crop
        arrays.append(arr)
        transforms.append(ResizeTransform((w, h), (nw, nh), scaled_w / w, scaled_h / h, off_x, off_y))
    min_h = min(a.shape[0] for a in arrays)
    min_w = min(a.shape[1] for a in arrays)
    for k, arr in enumerate(arrays):
        if arr.shape[:2] != (min_h, min_w):  # torchvision CenterCrop: Python's round of half the excess
            top, left = int(round((arr.shape[0] - min_h) / 2.0)), int(round((arr.shape[1] - min_w) / 2.0))
            arrays[k] = arr[top : top + min_h, left : left + min_w]
            t = transforms[k]
            transforms[k] = ResizeTransform(
                t.orig_size_wh, (min_w, min_h), t.scale_x, t.scale_y, t.offset_x - left, t.offset_y - top
            )
    batch = np.stack(arrays).astype(np.float32).transpose(0, 3, 1, 2) / np.float32(255.0)
    return np.ascontiguousarray(batch, dtype=np.float32), tuple(transforms)


def _squeeze_batch(name: str, array: np.ndarray, rank: int) -> np.ndarray:
    return strip_batch_axis(
        name,
        array,
        (None,) * rank,
        fix="export the model with `ffrecon export-model da3` "
        "(outputs depth, depth_conf [1,S,H,W], extrinsics [1,S,3,4], intrinsics [1,S,3,3])",
    )


def decode_da3_outputs(
    outputs: Mapping[str, np.ndarray],
    transforms: Sequence[ResizeTransform],
    names: Sequence[str],
    model: ModelInfo,
    *,
    max_depth_side: int | None = None,
) -> Prediction:
    """DA3 outputs for S frames to a :class:`Prediction` in original-photo pixels, world = frame 0.

    Args:
        outputs: ``depth``, ``depth_conf`` ``[1, S, H, W]``, ``extrinsics [1, S, 3, 4]`` (or
            ``[.., 4, 4]``) cam_from_world, ``intrinsics [1, S, 3, 3]`` network pixels (the leading
            batch axis is optional).
        transforms: the S transforms from :func:`preprocess_da3`; names: S frame names.
        max_depth_side: cap on the long side of the returned depth grids (None: original size).
    """
    require_outputs(
        outputs,
        OUTPUT_NAMES,
        fix="a Depth Anything 3 model must output depth, depth_conf, extrinsics and intrinsics "
        "(export it with `ffrecon export-model da3`)",
    )
    for key in OUTPUT_NAMES:
        check_finite(key, np.asarray(outputs[key]), model=model.path)
    depth = _squeeze_batch("depth", np.asarray(outputs["depth"]), 3)
    conf = _squeeze_batch("depth_conf", np.asarray(outputs["depth_conf"]), 3)
    cam_from_ref = _squeeze_batch(
        "extrinsics", np.asarray(outputs["extrinsics"], dtype=np.float64), 3
    )  # DA3's reference view
    K_net = _squeeze_batch("intrinsics", np.asarray(outputs["intrinsics"], dtype=np.float64), 3)
    s = len(transforms)
    if (
        depth.shape[0] != s
        or conf.shape != depth.shape
        or cam_from_ref.shape[0] != s
        or cam_from_ref.shape[1:] not in ((3, 4), (4, 4))
        or K_net.shape != (s, 3, 3)
    ):
        raise ModelError(
            f"model outputs disagree with the {s} input frames: depth {depth.shape}, depth_conf {conf.shape}, "
            f"extrinsics {cam_from_ref.shape}, intrinsics {K_net.shape}",
            "check that the model follows the da3 contract (`ffrecon inspect-model`)",
        )
    focal = K_net[:, [0, 1], [0, 1]]
    if not (focal > 0).all():
        raise ModelError(
            f"model output 'intrinsics' has non-positive focal lengths {focal.min():.3g}",
            "the camera decoder is broken or untrained; re-export (random weights: without --keep-untrained-heads)",
        )
    # DA3's world is its reference view's camera: re-express every pose relative to frame 0.
    cam_from_world = compose_poses(cam_from_ref[:, :3], invert_pose(cam_from_ref[0, :3])[None])
    return prediction_in_original_pixels(
        names, cam_from_world, K_net, depth, conf, transforms, model, max_depth_side=max_depth_side
    )


ADAPTER = MultiviewAdapter(
    family=ModelFamily.DA3,
    input_name=INPUT_NAME,
    output_names=OUTPUT_NAMES,
    preprocess=lambda images, mode: preprocess_da3(images, MODE_METHODS[mode]),
    decode=lambda outputs, transforms, names, model, max_side: decode_da3_outputs(
        outputs, transforms, names, model, max_depth_side=max_side
    ),
    modes=tuple(MODE_METHODS),
    world_frame="the first frame's camera (DA3's poses, relative to the reference view it picks, re-expressed)",
    description="Depth Anything 3: depth, depth_conf (1 + exp), extrinsics (cam_from_world), intrinsics; "
    "504-px processing",
)
