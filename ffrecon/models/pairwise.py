"""The DUSt3R-style pairwise path (docs/contracts.md, "Pairwise models"): pair graph, inference, global alignment.

A pairwise model sees two images at a time and returns both views' points in the first view's
camera frame. :func:`predict_pairwise` preprocesses the photos, runs the model over a pair graph,
aligns all pairs into one world (:mod:`ffrecon.models.global_alignment`) and maps the result back
to original-photo pixels. The model itself is any callable, so everything here runs on plain arrays.
"""

from __future__ import annotations

import enum
import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from PIL import Image
from tqdm.auto import tqdm

from ffrecon.checks import check_finite, check_number, require_outputs
from ffrecon.errors import FFReconError, InputError, ModelError
from ffrecon.models.alignment_init import AlignmentOptions, PairPrediction
from ffrecon.models.resize import ResizeTransform
from ffrecon.types import ModelFamily, ModelInfo, PinholeCamera, Prediction

if TYPE_CHECKING:
    from ffrecon.models.global_alignment import AlignmentResult

log = logging.getLogger("ffrecon.models.pairwise")

PATCH_SIZE = 16
LONG_SIDE = 512
SQUARE_SIDE = 224  # upstream's square mode (the *_224_linear checkpoints)
INPUT_NAMES = ("view1", "view2")
OUTPUT_NAMES = ("pts3d", "conf", "pts3d_in_other_view", "conf_in_other_view")
# MASt3R's optional outputs: view1's and view2's descriptors [B, H, W, D] (unit norm) and their
# confidences [B, H, W] (>= 0). Checked when present, not used yet (matching will use them).
DESCRIPTOR_NAMES = ("desc", "desc_conf", "desc_in_other_view", "desc_conf_in_other_view")

# A pairwise model: (view1 [B, 3, H, W], view2 [B, 3, H, W]) float32 in [-1, 1] -> the four outputs.
PairInfer = Callable[[np.ndarray, np.ndarray], Mapping[str, np.ndarray]]


class PairGraph(enum.Enum):
    COMPLETE = "complete"  # every pair of views
    SLIDING_WINDOW = "sliding_window"  # each view with the next ``window`` views (ordered captures)
    ONE_REFERENCE = "one_reference"  # every view with the reference view


def make_pairs(
    num_views: int,
    graph: PairGraph,
    *,
    window: int = 3,
    reference: int = 0,
    symmetric: bool = True,
    cyclic: bool = False,
) -> list[tuple[int, int]]:
    """Ordered view pairs ``(i, j)`` to run the model on.

    Args:
        num_views: N >= 2.
        graph: which pairs; SLIDING_WINDOW pairs ``i`` with ``i + 1 .. i + window`` (wrapping
            around when ``cyclic``), ONE_REFERENCE pairs ``reference`` with every other view.
        symmetric: also add ``(j, i)`` right after each ``(i, j)`` (DUSt3R's default; it gives every
            view its own-frame point map and halves the effect of the model's asymmetry).
    Returns:
        Distinct pairs, in a deterministic order.

    >>> make_pairs(4, PairGraph.SLIDING_WINDOW, window=1, symmetric=False)
    [(0, 1), (1, 2), (2, 3)]
    >>> make_pairs(3, PairGraph.ONE_REFERENCE, reference=1)
    [(1, 0), (0, 1), (1, 2), (2, 1)]
    """
    if num_views < 2:
        raise InputError(f"a pair graph needs at least 2 views, got {num_views}", "pass two or more images")
    if window < 1:
        raise FFReconError(f"sliding window must be >= 1, got {window}", "use window >= 1")
    if not 0 <= reference < num_views:
        raise FFReconError(
            f"reference view {reference} is not one of the {num_views} views", f"use a reference in 0..{num_views - 1}"
        )
    if graph is PairGraph.COMPLETE:
        base = [(i, j) for i in range(num_views) for j in range(i + 1, num_views)]
    elif graph is PairGraph.SLIDING_WINDOW:
        base = []
        for i in range(num_views):
            for k in range(1, window + 1):
                if cyclic or i + k < num_views:
                    base.append((i, (i + k) % num_views))
    elif graph is PairGraph.ONE_REFERENCE:
        base = [(reference, j) for j in range(num_views) if j != reference]
    else:
        raise FFReconError(f"unknown pair graph {graph!r}", f"use one of {[g.name for g in PairGraph]}")
    pairs: list[tuple[int, int]] = []
    seen: set[tuple[int, int]] = set()
    for i, j in base:
        for pair in ((i, j), (j, i)) if symmetric else ((i, j),):
            if pair[0] != pair[1] and pair not in seen:
                seen.add(pair)
                pairs.append(pair)
    return pairs


def network_size_hw(height: int, width: int, long_side: int = LONG_SIDE) -> tuple[int, int]:
    """The network input ``(H, W)`` upstream's ``load_images(size=long_side)`` gives a photo.

    The long side is resized to ``long_side`` (sides rounded), then each side is cropped down to a
    multiple of 16; a square photo is cropped to 4:3 landscape (upstream's ``square_ok=False``).
    ``long_side`` 224 is upstream's square mode: the short side goes to 224, centre square crop.

    >>> (network_size_hw(3024, 4032), network_size_hw(1000, 700), network_size_hw(800, 800),
    ...  network_size_hw(480, 640, 224))
    ((384, 512), (512, 352), (384, 512), (224, 224))
    """
    if long_side == SQUARE_SIDE:
        return (SQUARE_SIDE, SQUARE_SIDE)
    new_w, new_h = _reference_resize_wh(width, height, long_side)
    net_w, net_h = new_w // PATCH_SIZE * PATCH_SIZE, new_h // PATCH_SIZE * PATCH_SIZE
    if new_w == new_h:
        net_h = 3 * net_w // 4 // PATCH_SIZE * PATCH_SIZE
    return (net_h, net_w)


def _reference_resize_wh(width: int, height: int, long_side: int) -> tuple[int, int]:
    """Upstream ``_resize_pil_image``'s size: long side to ``long_side`` (224: short side to 224)."""
    edge = round(long_side * max(width / height, height / width)) if long_side == SQUARE_SIDE else long_side
    side = max(width, height)
    return round(width * edge / side), round(height * edge / side)


def preprocess_pairwise(
    images: Sequence[np.ndarray], long_side: int = LONG_SIDE, *, size_hw: tuple[int, int] | None = None
) -> tuple[np.ndarray, tuple[ResizeTransform, ...]]:
    """Resize and centre-crop photos for a DUSt3R-style model, recording the pixel mapping.

    Upstream's reference (``dust3r.utils.image.load_images``): each photo's long side is resized to
    ``long_side`` (PIL Lanczos when shrinking, bicubic otherwise; 224: the short side, for the square
    224 checkpoints), then centre-cropped (crop box from ``size // 2``) to the network size, and
    normalised as ``(x / 255 - 0.5) / 0.5``. One network size serves every photo (fixed-shape
    exports): :func:`network_size_hw` of the first photo unless ``size_hw`` fixes it. A photo that
    the reference resize does not cover at that size (another aspect ratio or orientation than the
    first photo) is instead scaled to cover it and centre-cropped, losing its margins, where upstream
    would give it its own size.

    Args:
        images: N images ``[H, W, 3]`` uint8 RGB (EXIF orientation applied).
        long_side: the reference long side (512 for the 512 checkpoints; 224 for the 224 ones).
        size_hw: fixed network size (the export's); its long side then replaces ``long_side``.
    Returns:
        ``(batch [N, 3, Hn, Wn] float32 RGB in [-1, 1], N transforms original -> network)``.
    """
    _check_rgb8(images)
    if size_hw is None:
        size_hw = network_size_hw(*images[0].shape[:2], long_side)
    else:
        long_side = max(size_hw)
    net_h, net_w = size_hw
    if net_h < PATCH_SIZE or net_w < PATCH_SIZE or net_h % PATCH_SIZE or net_w % PATCH_SIZE:
        raise InputError(
            f"network size {net_w}x{net_h} is not a positive multiple of {PATCH_SIZE}",
            f"use a size whose sides are multiples of {PATCH_SIZE}",
        )
    out = np.empty((len(images), 3, net_h, net_w), np.float32)
    transforms = []
    for k, image in enumerate(images):
        out[k], transform = _resize_and_crop(image, k, size_hw, long_side)
        transforms.append(transform)
    return out, tuple(transforms)


def _check_rgb8(images: Sequence[np.ndarray]) -> None:
    """Raise :class:`InputError` unless there are images and each is ``[H, W, 3]`` uint8."""
    if not images:
        raise InputError("no images to preprocess", "pass at least two images")
    for k, image in enumerate(images):
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise InputError(
                f"image {k} has shape {image.shape} and dtype {image.dtype}; expected [H, W, 3] uint8 RGB",
                "load images as 8-bit RGB",
            )


def _resize_and_crop(
    image: np.ndarray, k: int, size_hw: tuple[int, int], long_side: int
) -> tuple[np.ndarray, ResizeTransform]:
    """One photo (image ``k``) to ``[3, Hn, Wn]`` float32 in [-1, 1], and its transform (see
    :func:`preprocess_pairwise`)."""
    net_h, net_w = size_hw
    h, w = image.shape[:2]
    new_w, new_h = _reference_resize_wh(w, h, long_side)
    if new_w < net_w or new_h < net_h:  # not the reference: scale to cover the network size
        if abs(w / h - net_w / net_h) > 0.1 * net_w / net_h:
            log.warning(
                "image %d (%dx%d) has another aspect ratio than the network input %dx%d: its margins are cropped away",
                k,
                w,
                h,
                net_w,
                net_h,
            )
        s = max(net_w / w, net_h / h)
        new_w, new_h = max(net_w, round(w * s)), max(net_h, round(h * s))
    # upstream: Lanczos when shrinking
    resample = Image.Resampling.LANCZOS if max(new_w, new_h) < max(w, h) else Image.Resampling.BICUBIC
    resized = np.asarray(Image.fromarray(image).resize((new_w, new_h), resample), dtype=np.float32)
    left, top = new_w // 2 - net_w // 2, new_h // 2 - net_h // 2  # upstream's box: centre at size // 2
    crop = resized[top : top + net_h, left : left + net_w]
    # torchvision ToTensor + Normalize
    chw = ((crop / np.float32(255) - np.float32(0.5)) / np.float32(0.5)).transpose(2, 0, 1)
    return chw, ResizeTransform((w, h), (net_w, net_h), new_w / w, new_h / h, -float(left), -float(top))


def run_pairs(
    batch: np.ndarray, pairs: Sequence[tuple[int, int]], infer: PairInfer, batch_size: int = 4, *, model_name: str = ""
) -> list[PairPrediction]:
    """Run a pairwise model over ``pairs`` of ``batch`` images, ``batch_size`` pairs per call.

    Args:
        batch: ``[N, 3, H, W]`` float32 from :func:`preprocess_pairwise`.
        infer: maps ``view1, view2`` ``[B, 3, H, W]`` to ``pts3d``, ``conf``, ``pts3d_in_other_view``
            and ``conf_in_other_view`` (``[B, H, W, 3]`` and ``[B, H, W]``).
    Raises:
        ModelError: missing outputs, wrong shapes, NaN/inf, or confidences below 1.
    """
    if batch_size < 1:
        raise FFReconError(f"batch size must be >= 1, got {batch_size}", "use batch_size >= 1")
    _, _, h, w = batch.shape
    results: list[PairPrediction] = []
    with tqdm(total=len(pairs), desc="pairwise", unit="pair", disable=None) as bar:
        for start in range(0, len(pairs), batch_size):
            chunk = pairs[start : start + batch_size]
            view1 = np.ascontiguousarray(batch[[i for i, _ in chunk]])
            view2 = np.ascontiguousarray(batch[[j for _, j in chunk]])
            outputs = _check_outputs(infer(view1, view2), len(chunk), (h, w), model_name)
            for k, (i, j) in enumerate(chunk):
                results.append(
                    PairPrediction(
                        i,
                        j,
                        outputs["pts3d"][k],
                        outputs["conf"][k],
                        outputs["pts3d_in_other_view"][k],
                        outputs["conf_in_other_view"][k],
                    )
                )
            bar.update(len(chunk))
    return results


def _check_outputs(
    outputs: Mapping[str, np.ndarray], b: int, size_hw: tuple[int, int], model_name: str
) -> dict[str, np.ndarray]:
    require_outputs(
        outputs,
        OUTPUT_NAMES,
        fix=f"a DUSt3R-contract model must output {', '.join(OUTPUT_NAMES)} (docs/contracts.md, 'Pairwise models')",
    )
    checked = {}
    for name in OUTPUT_NAMES:
        value = np.asarray(outputs[name], dtype=np.float32)
        expected = (b, *size_hw, 3) if name.startswith("pts3d") else (b, *size_hw)
        if value.shape != expected:
            raise ModelError(
                f"pairwise model output '{name}' has shape {value.shape}; expected {expected}",
                "outputs must have the input's resolution (docs/contracts.md, 'Pairwise models')",
            )
        check_finite(name, value, model=model_name)
        if name.startswith("conf") and value.min() < 1.0 - 1e-3:
            raise ModelError(
                f"pairwise model output '{name}' has values down to {value.min():.3g}; confidences must be >= 1",
                "export the model with its confidence activation (1 + exp(x)), not raw logits",
            )
        checked[name] = value
    for name in (n for n in DESCRIPTOR_NAMES if n in outputs):  # MASt3R: checked and passed on, not used yet
        value = np.asarray(outputs[name], dtype=np.float32)
        is_desc = name in ("desc", "desc_in_other_view")
        if value.shape[:3] != (b, *size_hw) or value.ndim != (4 if is_desc else 3):
            raise ModelError(
                f"pairwise model output '{name}' has shape {value.shape}; "
                f"expected {(b, *size_hw, 'D') if is_desc else (b, *size_hw)}",
                "export MASt3R with `ffrecon export-model mast3r`",
            )
        check_finite(name, value, model=model_name)
        checked[name] = value
    return checked


def downsample_pair(pair: PairPrediction, stride: int) -> PairPrediction:
    """Average ``stride x stride`` blocks of a pair's maps (H and W must be multiples of ``stride``).

    Block ``(r, c)`` covers the network pixels whose centres surround ``((c + 0.5) s, (r + 0.5) s)``,
    which is the centre of pixel ``(r, c)`` of the grid scaled by ``1 / s`` (COLMAP rule), so the
    coarse maps keep the same principal point in scaled pixels.
    """
    h, w = pair.conf_i.shape
    if h % stride or w % stride:
        raise FFReconError(
            f"alignment stride {stride} does not divide the {w}x{h} maps",
            "use a stride that divides 16 (1, 2, 4, 8 or 16)",
        )

    def pool(a: np.ndarray) -> np.ndarray:
        return a.reshape(h // stride, stride, w // stride, stride, *a.shape[2:]).mean(axis=(1, 3)).astype(np.float32)

    return PairPrediction(
        pair.i, pair.j, pool(pair.pts_i_in_i), pool(pair.conf_i), pool(pair.pts_j_in_i), pool(pair.conf_j)
    )


@dataclass(frozen=True, kw_only=True)
class PairwiseOptions:
    graph: PairGraph = PairGraph.COMPLETE
    window: int = 3  # SLIDING_WINDOW: neighbours after each view
    cyclic: bool = False  # SLIDING_WINDOW: wrap around (closed loops)
    reference: int = 0  # ONE_REFERENCE: the reference view
    symmetric: bool = True  # run (j, i) as well as (i, j)
    long_side: int = LONG_SIDE
    size_hw: tuple[int, int] | None = None  # force the network input size (fixed-shape exports)
    batch_size: int = 4  # pairs per model call
    align_stride: int = 2  # align on maps averaged over stride x stride blocks (CPU time / stride^2)
    alignment: AlignmentOptions = field(default_factory=AlignmentOptions)
    max_depth_side: int | None = 1024  # cap on stored depth grids (None: original resolution)

    def __post_init__(self) -> None:
        for name in ("window", "batch_size", "align_stride"):
            check_number(f"PairwiseOptions.{name}", getattr(self, name), low=1, integer=True)
        check_number("PairwiseOptions.reference", self.reference, low=0, integer=True)
        check_number("PairwiseOptions.long_side", self.long_side, low=PATCH_SIZE, integer=True)
        check_number("PairwiseOptions.max_depth_side", self.max_depth_side, low=1, integer=True, allow_none=True)
        if PATCH_SIZE % self.align_stride:
            raise InputError(
                f"PairwiseOptions.align_stride {self.align_stride} does not divide the {PATCH_SIZE}-pixel patches",
                f"set align_stride to a divisor of {PATCH_SIZE} (1, 2, 4, 8 or 16)",
            )


def predict_pairwise(
    images: Sequence[np.ndarray],
    names: Sequence[str],
    infer: PairInfer,
    model: ModelInfo,
    options: PairwiseOptions = PairwiseOptions(),
) -> Prediction:
    """Run a pairwise model over a pair graph and globally align the pairs into one :class:`Prediction`.

    Args:
        images: N >= 2 images ``[H, W, 3]`` uint8 RGB; names: N frame names.
        infer: the model (see :func:`run_pairs`); model: what it is (its family must be PAIRWISE).
    Returns:
        Poses (world = the first image's camera, scale of the pairs), intrinsics, depth and
        confidence in original-photo pixels (0 where the crop cut the photo).
    """
    if len(images) != len(names):
        raise InputError(f"{len(images)} images but {len(names)} names", "pass one name per image")
    if model.family is not ModelFamily.PAIRWISE:
        raise ModelError(
            f"{model.path} is a {model.family.value} model, not a pairwise one",
            "use predict_multiview for VGGT-contract models",
        )
    pairs = make_pairs(
        len(images),
        options.graph,
        window=options.window,
        reference=options.reference,
        symmetric=options.symmetric,
        cyclic=options.cyclic,
    )
    batch, transforms = preprocess_pairwise(images, options.long_side, size_hw=options.size_hw)
    log.info(
        "pairwise model on %d images at %dx%d: %d pairs (%s)",
        len(images),
        batch.shape[3],
        batch.shape[2],
        len(pairs),
        options.graph.value,
    )
    predictions = run_pairs(batch, pairs, infer, options.batch_size, model_name=model.path)
    stride = options.align_stride
    if stride > 1:
        predictions = [downsample_pair(p, stride) for p in predictions]
    size_hw = (batch.shape[2] // stride, batch.shape[3] // stride)
    from ffrecon.models.global_alignment import global_align  # torch and kornia: only pairwise models need them

    result = global_align(predictions, size_hw, options.alignment)
    cameras, depths, confs = _alignment_in_original_pixels(result, transforms, stride, options.max_depth_side)
    return Prediction(tuple(names), result.cam_from_world, cameras, depths, confs, model)


def _alignment_in_original_pixels(
    result: AlignmentResult, transforms: Sequence[ResizeTransform], stride: int, max_depth_side: int | None
) -> tuple[tuple[PinholeCamera, ...], tuple[np.ndarray, ...], tuple[np.ndarray, ...]]:
    """Each view's camera, depth and confidence from the alignment grid back to original-photo pixels."""
    size_hw = result.size_hw
    cameras, depths, confs = [], [], []
    for k, t in enumerate(transforms):
        # The alignment grid is the network grid scaled by 1 / stride (no half-pixel terms).
        grid = ResizeTransform(
            t.orig_size_wh,
            (size_hw[1], size_hw[0]),
            t.scale_x / stride,
            t.scale_y / stride,
            t.offset_x / stride,
            t.offset_y / stride,
        )
        cameras.append(grid.camera_to_original(result.K(k)))
        depths.append(grid.map_to_original(result.depth[k], max_side=max_depth_side))
        confs.append(grid.map_to_original(result.conf[k], max_side=max_depth_side))
    return tuple(cameras), tuple(depths), tuple(confs)
