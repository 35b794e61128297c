"""The capture's masks (``--masks``): found by either naming convention, scaled with their downscaled
photos (staying binary), missing ones used whole, and bad ones refused with the problem and the fix."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ffrecon.capture import CaptureOptions, run_capture
from ffrecon.errors import InputError


def _photos(folder, n=3, size=(400, 300)):
    folder.mkdir()
    rng = np.random.default_rng(0)
    for k in range(n):
        cv2.imwrite(str(folder / f"p{k}.jpg"), rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8))
    return folder


def test_masks_by_either_name_scaled_with_their_photos(tmp_path):
    photos, masks = _photos(tmp_path / "photos"), tmp_path / "masks"
    masks.mkdir()
    ignore = np.full((300, 400), 255, np.uint8)
    ignore[100:200, 50:150] = 0
    cv2.imwrite(str(masks / "p0.png"), ignore)  # nerfstudio's <stem>.png
    rgba = np.dstack([np.full((300, 400, 3), 9, np.uint8), ignore])
    cv2.imwrite(str(masks / "p1.jpg.png"), np.where(rgba[..., 3:] > 0, rgba, 0).astype(np.uint8))  # COLMAP's name
    capture = run_capture(photos, CaptureOptions(masks=masks, max_image_size=200), tmp_path / "run")
    assert [f.size_wh for f in capture.frames] == [(200, 150)] * 3
    got = capture.read_masks()
    assert [m.shape for m in got] == [(150, 200)] * 3
    for k in (0, 1):  # halved with the photo; still 0/255 (nearest), the same rectangle
        assert not got[k][50:100, 25:75].any() and got[k].sum() == 150 * 200 - 50 * 50
    assert got[2].all()  # no mask given: the photo is used whole
    assert {p.name for p in capture.mask_dir.iterdir()} == {"p0.jpg.png", "p1.jpg.png", "p2.jpg.png"}


@pytest.mark.parametrize(
    ("make", "says"),
    [
        (lambda m: None, "holds no mask"),
        (lambda m: cv2.imwrite(str(m / "p0.png"), np.zeros((10, 10), np.uint8)), "make each mask the size"),
        (lambda m: (m / "p0.png").write_bytes(b"not a png"), "cannot be read"),
    ],
)
def test_bad_masks_are_refused_with_the_fix(tmp_path, make, says):
    photos, masks = _photos(tmp_path / "photos"), tmp_path / "masks"
    masks.mkdir()
    make(masks)
    with pytest.raises(InputError, match=says):
        run_capture(photos, CaptureOptions(masks=masks), tmp_path / "run")


def test_masks_must_be_a_folder(tmp_path):
    photos = _photos(tmp_path / "photos")
    with pytest.raises(InputError, match="is not a folder"):
        run_capture(photos, CaptureOptions(masks=tmp_path / "nope"), tmp_path / "run")
