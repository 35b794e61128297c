"""The monocular depth contract (Depth Anything V1/V2, DPT): one photo in, one depth map out.

A ``monodepth`` ONNX file (``ffrecon export-model monodepth``) takes ``pixel_values [B, 3, H, W]``
float32 RGB in [0, 1] and returns ``predicted_depth [B, H, W]``, either relative inverse depth
(``ffrecon.depth_kind = relative_inverse``: disparity-like, larger is nearer, unknown scale and
shift) or metric depth in metres (``metric``).

Preprocessing follows ``transformers``' ``DPTImageProcessor`` with Depth Anything's settings
(``size`` 518x518, ``keep_aspect_ratio``, ``ensure_multiple_of`` 14, bicubic): one scale for both
axes, the one closer to 1 of ``518 / H`` and ``518 / W``, then each side rounded to the nearest
multiple of 14 (Python's ``round``); the resize is PIL's bicubic on the 8-bit photo, as the
processor's PIL backend does (its torchvision backend's antialiased bicubic differs by a few grey
levels). The normalisation is inside the file.

Decoding (one photo): the depth map is brought to the original pixels with bicubic interpolation,
as ``post_process_depth_estimation`` does; relative inverse depth ``d`` becomes depth under a stated
assumption (:data:`RELATIVE_DEPTH_ASSUMPTION`); the camera is the photo's EXIF focal when known,
else a :data:`DEFAULT_HFOV_DEG` guess, principal point at the centre, pose identity.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from PIL import Image

from ffrecon.checks import check_finite
from ffrecon.errors import InputError, ModelError
from ffrecon.models.adapters import MultiviewAdapter, PreprocessMode
from ffrecon.models.resize import ResizeTransform
from ffrecon.types import ModelFamily, ModelInfo, PinholeCamera, Prediction

PATCH_SIZE = 14
TARGET_SIZE = 518
INPUT_NAME = "pixel_values"
OUTPUT_NAMES = ("predicted_depth",)
DEPTH_KINDS = ("relative_inverse", "metric")
DEFAULT_HFOV_DEG = 60.0  # horizontal field of view assumed when the photo has no EXIF focal length
RELATIVE_DEPTH_ASSUMPTION = (
    "relative inverse depth d turned into depth as median(d) / d: shift assumed 0, "
    "scale chosen so that the median depth is 1 (arbitrary units); d below 1/1000 of the median (sky) left unknown"
)
MIN_INVERSE_FRACTION = 1e-3  # relative inverse depth below this fraction of the median: "at infinity" (sky), unknown
REFERENCE_MODE = PreprocessMode.CROP  # the family's one (reference) preprocessing, the processor's resize


@dataclass(frozen=True)
class ProcessorSettings:
    """The ``DPTImageProcessor`` settings ffrecon reproduces (defaults: Depth Anything's)."""

    size_hw: tuple[int, int] = (TARGET_SIZE, TARGET_SIZE)
    keep_aspect_ratio: bool = True
    multiple: int = PATCH_SIZE
    resample: int = 3  # PIL's code: 3 bicubic, 2 bilinear

    @staticmethod
    def from_model(model: ModelInfo) -> "ProcessorSettings":
        """From the ``ffrecon.monodepth.processor`` metadata (the checkpoint's preprocessor_config.json)."""
        metadata = dict(getattr(model, "metadata", None) or {})
        try:
            given = json.loads(metadata.get("ffrecon.monodepth.processor") or "{}")
            size = given.get("size", {})
            size_hw = (int(size["height"]), int(size["width"])) if "height" in size else ProcessorSettings.size_hw
            return ProcessorSettings(
                size_hw,
                bool(given.get("keep_aspect_ratio", True)),
                int(given.get("ensure_multiple_of", PATCH_SIZE)),
                int(given.get("resample", 3)),
            )
        except (ValueError, TypeError, KeyError, AttributeError) as exc:
            raise ModelError(
                f"{model.path}: unreadable ffrecon.monodepth.processor metadata ({exc})",
                "re-export the model with `ffrecon export-model monodepth`",
            ) from exc


def network_size_hw(height: int, width: int, settings: ProcessorSettings = ProcessorSettings()) -> tuple[int, int]:
    """``DPTImageProcessor``'s output size (``get_resize_output_image_size``) for a photo.

    >>> network_size_hw(480, 640), network_size_hw(640, 480), network_size_hw(300, 400)
    ((518, 686), (686, 518), (392, 518))
    """
    scale_h, scale_w = settings.size_hw[0] / height, settings.size_hw[1] / width
    if settings.keep_aspect_ratio:  # scale as little as possible
        if abs(1 - scale_w) < abs(1 - scale_h):
            scale_h = scale_w
        else:
            scale_w = scale_h
    m = settings.multiple
    return round(scale_h * height / m) * m, round(scale_w * width / m) * m


def preprocess_monodepth(
    images: Sequence[np.ndarray],
    mode: PreprocessMode = REFERENCE_MODE,
    settings: ProcessorSettings = ProcessorSettings(),
) -> tuple[np.ndarray, tuple[ResizeTransform, ...]]:
    """The processor's resize (module docstring), with the bookkeeping to undo it.

    Args:
        images: B images ``[H, W, 3]`` uint8 RGB. Photos that preprocess to different sizes are
            centre-cropped to the smallest, so that they stack.
        mode: the family has one preprocessing; settings: the processor's (default Depth Anything's).
    Returns:
        ``([B, 3, Hn, Wn] float32 RGB in [0, 1], B transforms original -> network)``.
    """
    arrays, transforms = [], []
    for image in images:
        h, w = image.shape[:2]
        nh, nw = network_size_hw(h, w, settings)
        arr = np.asarray(Image.fromarray(image).resize((nw, nh), Image.Resampling(settings.resample)))
        arrays.append(arr)
        transforms.append(ResizeTransform((w, h), (nw, nh), nw / w, nh / h))
    min_h, min_w = min(a.shape[0] for a in arrays), min(a.shape[1] for a in arrays)
    for k, arr in enumerate(arrays):
        if arr.shape[:2] != (min_h, min_w):
            top, left = (arr.shape[0] - min_h) // 2, (arr.shape[1] - min_w) // 2
            arrays[k] = arr[top : top + min_h, left : left + min_w]
            t = transforms[k]
            transforms[k] = ResizeTransform(
                t.orig_size_wh, (min_w, min_h), t.scale_x, t.scale_y, t.offset_x - left, t.offset_y - top
            )
    batch = np.stack(arrays).astype(np.float32).transpose(0, 3, 1, 2) / np.float32(255.0)
    return np.ascontiguousarray(batch, dtype=np.float32), tuple(transforms)


def guessed_camera(width: int, height: int, focal_px: float | None = None) -> PinholeCamera:
    """The camera of one photo: the EXIF focal (pixels of this photo) if known, else a 60-degree guess.

    >>> round(guessed_camera(640, 480).fx, 2)
    554.26
    """
    fx = float(focal_px) if focal_px else float((width / 2) / np.tan(np.radians(DEFAULT_HFOV_DEG) / 2))
    return PinholeCamera(int(width), int(height), fx, fx, width / 2, height / 2)


def depth_from_inverse(inverse: np.ndarray) -> np.ndarray:
    """Relative inverse depth to depth under :data:`RELATIVE_DEPTH_ASSUMPTION` (0 where unknown).

    Values at or below :data:`MIN_INVERSE_FRACTION` of the median positive value (sky, or bicubic
    undershoot next to it) stay unknown instead of going to infinity; the scale is the median over
    the rest, so the median of the returned depth is 1.

    >>> depth_from_inverse(np.array([1.0, 2.0, 4.0, 2.0, 0.0, 1e-6]))
    array([2. , 1. , 0.5, 1. , 0. , 0. ], dtype=float32)
    """
    positive = inverse > 0
    if not positive.any():
        return np.zeros_like(inverse, dtype=np.float32)
    valid = inverse > MIN_INVERSE_FRACTION * np.median(inverse[positive])
    median = np.median(inverse[valid])
    return np.where(valid, median / np.where(valid, inverse, 1.0), 0.0).astype(np.float32)


def describe_assumptions(depth_kind: str, focal_px: float | None) -> str:
    """One sentence for the report: what the decoded geometry assumed."""
    camera = (
        "the photo's EXIF focal length"
        if focal_px
        else f"a guessed {DEFAULT_HFOV_DEG:.0f}-degree horizontal field of view (no EXIF focal length)"
    )
    depth = "metric depth used as predicted" if depth_kind == "metric" else RELATIVE_DEPTH_ASSUMPTION
    return f"monocular depth: {depth}; camera from {camera}; pose identity"


def _model_depth_kind(model: ModelInfo) -> str:
    metadata = dict(getattr(model, "metadata", None) or {})  # ModelInfo.metadata (proposed)
    return metadata.get("ffrecon.depth_kind", DEPTH_KINDS[0])


def decode_monodepth(
    outputs: Mapping[str, np.ndarray],
    transforms: Sequence[ResizeTransform],
    names: Sequence[str],
    model: ModelInfo,
    max_depth_side: int | None = None,
    *,
    focal_px: float | None = None,
    depth_kind: str | None = None,
) -> Prediction:
    """One photo's ``predicted_depth`` to a :class:`Prediction` in original-photo pixels.

    Args:
        outputs: ``predicted_depth [1, H, W]`` (or ``[1, 1, H, W]``).
        transforms: the one transform from :func:`preprocess_monodepth`; names: the one frame name.
        max_depth_side: cap on the long side of the returned depth grid (None: original size).
        focal_px: the photo's focal length in its own pixels (EXIF), if known.
        depth_kind: ``relative_inverse`` or ``metric`` (None: the model's ``ffrecon.depth_kind``).
    Returns:
        world = the camera (identity pose); depth in the units above; confidence 1 where the depth
        is valid, 0 elsewhere.
    """
    if len(transforms) != 1 or len(names) != 1:
        raise InputError(
            f"a monocular depth model reconstructs one photo, got {len(names)}",
            "pass a single photo, or use a multi-view model (VGGT, Depth Anything 3) for several",
        )
    kind = depth_kind or _model_depth_kind(model)
    if kind not in DEPTH_KINDS:
        raise ModelError(
            f"unknown depth kind '{kind}'",
            f"the model's ffrecon.depth_kind must be one of {', '.join(DEPTH_KINDS)}; "
            "re-export with `ffrecon export-model monodepth`",
        )
    if OUTPUT_NAMES[0] not in outputs:
        raise ModelError(
            f"model outputs lack 'predicted_depth'; got {sorted(outputs)}",
            "a monocular depth model must output predicted_depth [B, H, W] "
            "(export it with `ffrecon export-model monodepth`)",
        )
    raw = np.asarray(outputs[OUTPUT_NAMES[0]], dtype=np.float32)
    check_finite(OUTPUT_NAMES[0], raw, model=model.path)
    net = raw[:, 0] if raw.ndim == 4 and raw.shape[1] == 1 else raw
    if net.ndim != 3 or net.shape[0] != 1:
        raise ModelError(
            f"model output 'predicted_depth' has shape {raw.shape}; expected [1, H, W] for one photo",
            "export the model with `ffrecon export-model monodepth`",
        )
    t = transforms[0]
    # Bicubic at the original pixel centres: F.interpolate(mode="bicubic", align_corners=False).
    value = t.map_to_original(net[0], max_side=max_depth_side, interpolation=cv2.INTER_CUBIC)
    depth = (
        depth_from_inverse(value) if kind == "relative_inverse" else np.where(value > 0, value, 0.0).astype(np.float32)
    )
    conf = (depth > 0).astype(np.float32)
    camera = guessed_camera(*t.orig_size_wh, focal_px=focal_px)
    cam_from_world = np.concatenate([np.eye(3), np.zeros((3, 1))], axis=1)[None]
    return Prediction(tuple(names), cam_from_world, (camera,), (depth,), (conf,), model)


def predict_monodepth(
    image: np.ndarray,
    name: str,
    infer: Callable[[np.ndarray], Mapping[str, np.ndarray]],
    model: ModelInfo,
    *,
    focal_px: float | None = None,
    max_depth_side: int | None = None,
) -> Prediction:
    """Preprocess one photo, run the model (``infer``: ``pixel_values`` batch to outputs), decode.

    Args:
        image: ``[H, W, 3]`` uint8 RGB; name: its frame name.
        focal_px: its focal length in its own pixels (EXIF), if known.
        max_depth_side: the longest side depth is returned at (None: the photo's size); the family has
            one preprocessing, with the processor settings the export recorded.
    """
    batch, transforms = preprocess_monodepth([image], settings=ProcessorSettings.from_model(model))
    return decode_monodepth(infer(batch), transforms, [name], model, max_depth_side, focal_px=focal_px)


ADAPTER = MultiviewAdapter(
    family=ModelFamily.MONODEPTH,
    input_name=INPUT_NAME,
    output_names=OUTPUT_NAMES,
    preprocess=lambda images, mode: preprocess_monodepth(images, mode),
    decode=lambda outputs, transforms, names, model, max_side: decode_monodepth(
        outputs, transforms, names, model, max_side
    ),
    modes=(REFERENCE_MODE,),
    world_frame="the photo's camera (one photo; identity pose)",
    description="monocular depth: predicted_depth (relative inverse or metric); "
    f"camera from EXIF or a {DEFAULT_HFOV_DEG:.0f}-degree guess",
)
