"""Fixtures for tests that build the real upstream architectures (tiny configurations, random weights).

The upstream code lives beside the checkout in ``../shared/upstream`` (CI has it; a user's clone may
not): tests that need it skip with that reason when it is absent.
"""

from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[3]
UPSTREAM = REPO.parent / "shared" / "upstream"
PHOTOS = REPO.parent / "shared" / "data" / "lund"


def upstream_dir(name: str) -> Path:
    """``../shared/upstream/<name>``, or skip the test when it is not there."""
    path = UPSTREAM / name
    if not path.is_dir():
        pytest.skip(f"needs the upstream {name} code in {path} (present in CI; absent in a plain clone)")
    return path


def real_photos(count: int, size_wh: tuple[int, int] = (640, 480)) -> list[np.ndarray]:
    """``count`` real street photos (lund, BSD-2) resized to ``size_wh``, as [H, W, 3] uint8 RGB."""
    from PIL import Image

    files = sorted(PHOTOS.glob("*.jpg"))[:count]
    if len(files) < count:
        pytest.skip(f"needs {count} photos in {PHOTOS}")
    return [np.asarray(Image.open(f).convert("RGB").resize(size_wh, Image.Resampling.LANCZOS)) for f in files]


@pytest.fixture
def landscape_and_portrait():
    """Two real photos as 640x480 landscape and two as 480x640 portrait (the same photos, cropped)."""
    land = real_photos(3, (640, 480))
    portrait = [np.ascontiguousarray(p[:, 186:666]) for p in real_photos(3, (853, 640))]
    return {"landscape": land, "portrait": portrait}


@pytest.fixture
def photo_folder(tmp_path) -> Path:
    """Four real 640x480 photos written as JPEG files: input for ``ffrecon run``."""
    from PIL import Image

    folder = tmp_path / "photos"
    folder.mkdir()
    for k, image in enumerate(real_photos(4)):
        Image.fromarray(image).save(folder / f"{k:02d}.jpg", quality=95)
    return folder
