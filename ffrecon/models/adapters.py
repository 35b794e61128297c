"""One adapter per multi-view model family: its input, its reference preprocessing and its decoding.

Every multi-view family (VGGT, Depth Anything 3, Pi3, MapAnything, one-image monocular depth) runs
through the same chunked loop (:func:`ffrecon.models.multiview.predict_multiview`): preprocess the
frames of one call, run the model, decode its outputs to a :class:`~ffrecon.types.Prediction` in the
original photos' pixels, then merge chunks. Only the three functions below differ per family.
The pairwise family (DUSt3R, MASt3R) has its own loop in :mod:`ffrecon.models.pairwise`.
"""

from __future__ import annotations

import enum
import importlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ffrecon.models.resize import ResizeTransform
from ffrecon.types import ModelFamily, ModelInfo, Prediction


class PreprocessMode(enum.Enum):
    CROP = "crop"  # the family's reference resize-and-crop (VGGT: width 518, centre-crop height to 518)
    PAD = "pad"  # longest side to the target, padded (VGGT: white, to a square)
    RESIZE = "resize"  # longest side to the target, sides to the patch multiple, no crop (DA3's reference)


# preprocess(images [H, W, 3] uint8 RGB, mode) -> (model input batch, one transform per image)
Preprocess = Callable[[Sequence[np.ndarray], PreprocessMode], tuple[np.ndarray, tuple[ResizeTransform, ...]]]
# decode(outputs by name, transforms, frame names, model info, max_depth_side) -> Prediction
Decode = Callable[
    [Mapping[str, np.ndarray], Sequence[ResizeTransform], Sequence[str], ModelInfo, "int | None"], Prediction
]


@dataclass(frozen=True)
class MultiviewAdapter:
    family: ModelFamily
    input_name: str  # the one image input, [S, 3, H, W] float32 (as the preprocessing returns it)
    output_names: tuple[str, ...]  # outputs the family must declare (detection) and decode needs
    preprocess: Preprocess
    decode: Decode
    modes: tuple[PreprocessMode, ...] = (PreprocessMode.CROP,)  # the first is the family's reference default
    world_frame: str = "the first frame's camera"  # what the decoded world frame is, for the report
    camera_outputs: str = "cameras"  # the output(s) cameras are decoded from, named in validation errors
    description: str = ""


# family -> module holding ``ADAPTER`` (imported lazily: each pulls in only what it needs).
ADAPTER_MODULES = {
    ModelFamily.MULTIVIEW: "ffrecon.models.vggt",
    ModelFamily.DA3: "ffrecon.models.da3",
    ModelFamily.PI3: "ffrecon.models.pi3",
    ModelFamily.MAPANYTHING: "ffrecon.models.mapanything",
    ModelFamily.MONODEPTH: "ffrecon.models.monodepth",
}


def adapter_for(family: ModelFamily) -> MultiviewAdapter:
    """The adapter of a multi-view family (KeyError for the pairwise family)."""
    return importlib.import_module(ADAPTER_MODULES[family]).ADAPTER
