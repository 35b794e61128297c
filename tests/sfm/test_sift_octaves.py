"""Which octave SIFT starts from (``SiftOptions``, issue 40): small images are upsampled 2x, larger ones start at
their own size, or at half of it in a long capture (``coarse_from_images``), where each frame overlaps many others
and SIFT was most of ``--quick``'s CPU. A sparse capture keeps every feature."""

import numpy as np
from PIL import Image

from ffrecon.sfm.features import SiftOptions, _octave_groups
from ffrecon.sfm.refine.options import QUICK_SIFT


def _folder(tmp_path, sizes):
    names = []
    for k, (w, h) in enumerate(sizes):
        names.append(f"f{k:03d}.png")
        Image.fromarray(np.zeros((h, w, 3), np.uint8)).save(tmp_path / names[-1])
    return names


def test_a_long_capture_of_large_images_starts_at_half_size_and_small_images_are_upsampled(tmp_path):
    names = _folder(tmp_path, [(640, 480)] * 46 + [(320, 240)])
    assert _octave_groups(tmp_path, names, QUICK_SIFT) == {0: names[:46], -1: names[46:]}  # 47 images: not yet coarse
    names = _folder(tmp_path, [(640, 480)] * 47 + [(320, 240)])
    assert _octave_groups(tmp_path, names, QUICK_SIFT) == {1: names[:47], -1: names[47:]}
    assert QUICK_SIFT.coarse_from_images == 48


def test_without_coarse_or_upsampling_every_image_gets_the_first_octave(tmp_path):
    names = _folder(tmp_path, [(640, 480)] * 3)
    assert _octave_groups(tmp_path, names, SiftOptions()) == {-1: names}  # COLMAP's default, the cross-check's
    plain = SiftOptions(first_octave=0, upsample_below_px=500)
    assert _octave_groups(tmp_path, names, plain) == {0: names}
