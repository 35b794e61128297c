"""``ffrecon export-model``: upstream PyTorch models to ONNX files that ffrecon's runner detects and decodes.

One module per family builds the upstream architecture (from a checkpoint, with random weights at
full size, or at a tiny configuration for tests) and wraps it with ffrecon's contract names; the
shared code in :mod:`.common` exports, verifies and records metadata.
"""

from __future__ import annotations

import importlib
import logging
from dataclasses import dataclass, replace
from pathlib import Path

from ffrecon.errors import FFReconError, InputError
from ffrecon.models.exporting.common import ExportReport, ModelExportOptions, export_spec

log = logging.getLogger("ffrecon.export_model")


@dataclass(frozen=True)
class FamilyEntry:
    module: str  # ffrecon.models.exporting.<module> with build(options, size_hw) and size_for_photo(h, w)
    summary: str


FAMILIES: dict[str, FamilyEntry] = {
    "vggt": FamilyEntry("vggt", "VGGT-1B (facebookresearch/vggt): multi-view cameras, depth, points"),
    "da3": FamilyEntry("da3", "Depth Anything 3 (PyPI depth-anything-3): multi-view or one image, depth, cameras"),
    "pi3": FamilyEntry("pi3", "Pi3 (yyfz/Pi3): multi-view, permutation-equivariant, world_from_cam poses"),
    "dust3r": FamilyEntry("dust3r", "DUSt3R (naver/dust3r): pairwise point maps, globally aligned by ffrecon"),
    "mast3r": FamilyEntry("dust3r", "MASt3R (naver/mast3r): DUSt3R's outputs plus local descriptors"),
    "monodepth": FamilyEntry(
        "monodepth", "monocular depth (Depth Anything V2 / DPT via transformers): one image, depth"
    ),
}


def family_module(family: str):
    if family not in FAMILIES:
        raise FFReconError(f"unknown model family '{family}'", f"use one of: {', '.join(FAMILIES)}")
    return importlib.import_module(f"ffrecon.models.exporting.{FAMILIES[family].module}")


def photo_size_hw(path: Path) -> tuple[int, int]:
    """``(height, width)`` of a photo, or of the first photo in a folder, upright (EXIF applied)."""
    from PIL import Image, ImageOps

    from ffrecon.capture.images import IMAGE_EXTENSIONS

    path = Path(path)
    files = (
        [path]
        if path.is_file()
        else sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)
        if path.is_dir()
        else []
    )
    if not files:
        raise InputError(
            f"no photo found at {path}",
            "pass a photo, or a folder of photos, the model will be used on (or --height/--width)",
        )
    try:
        with Image.open(files[0]) as image:
            w, h = ImageOps.exif_transpose(image).size
    except Exception as exc:  # PIL raises several types for unreadable files
        raise InputError(f"cannot read {files[0]}: {exc}", "pass a readable photo") from exc
    return h, w


def export_model(options: ModelExportOptions) -> ExportReport:
    """Build the family's upstream model, export it to ``options.out`` and verify it."""
    module = family_module(options.family)
    size_hw = options.size_hw
    if size_hw is None and options.photos is not None:
        size_hw = module.size_for_photo(*photo_size_hw(options.photos))
        log.info("input size %dx%d from the photos at %s", size_hw[1], size_hw[0], options.photos)
    size_hw = size_hw or module.DEFAULT_SIZE_HW
    patch = getattr(module, "PATCH_SIZE", 14)
    if size_hw[0] % patch or size_hw[1] % patch or min(size_hw) <= 0:
        raise FFReconError(
            f"input size {size_hw[1]}x{size_hw[0]} is not a multiple of {options.family}'s patch size {patch}",
            f"use --height and --width that are multiples of {patch}",
        )
    options = replace(options, size_hw=size_hw)
    try:
        spec = module.build(options, size_hw)
    except ImportError as exc:  # upstream code importing an optional package of its own deep inside
        missing = getattr(exc, "name", None) or str(exc)
        raise InputError(
            f"building {options.family} needs the Python package '{missing}', which is not installed",
            f"pip install 'ffrecon[export]'; if '{missing}' is not among its packages, "
            f"install it (pip install {missing})",
        ) from exc
    return export_spec(spec, options)
