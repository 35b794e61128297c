"""Known intrinsics the user gives (``--intrinsics FILE``), in COLMAP's ``cameras.txt`` form.

Either one camera for every photo (a ``cameras.txt`` with one line: ``CAMERA_ID MODEL WIDTH HEIGHT
PARAMS...``), or one per photo (the photo's file name in place of the id: ``NAME MODEL WIDTH HEIGHT
PARAMS...``). Models: ``SIMPLE_PINHOLE`` (f, cx, cy), ``PINHOLE`` (fx, fy, cx, cy), and COLMAP's lens
models with zero distortion (``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV``). Values are in the pixels of the
given ``WIDTH x HEIGHT`` and follow COLMAP's pixel-centre rule; they are scaled to each frame as captured.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ffrecon.errors import InputError
from ffrecon.types import PinholeCamera

# model -> (number of parameters, index of fx, fy, cx, cy, first distortion parameter)
_MODELS = {
    "SIMPLE_PINHOLE": (3, 0, 0, 1, 2, 3),
    "PINHOLE": (4, 0, 1, 2, 3, 4),
    "SIMPLE_RADIAL": (4, 0, 0, 1, 2, 3),
    "RADIAL": (5, 0, 0, 1, 2, 3),
    "OPENCV": (8, 0, 1, 2, 3, 4),
}
FIX = "write one line per camera as in COLMAP's cameras.txt: ID (or the photo's name) MODEL WIDTH HEIGHT PARAMS"


@dataclass(frozen=True)
class KnownIntrinsics:
    """The cameras of ``path``: ``shared`` for every photo, or ``per_image`` by photo name."""

    path: Path
    shared: PinholeCamera | None
    per_image: tuple[tuple[str, PinholeCamera], ...] = ()

    def camera(self, name: str, size_wh: tuple[int, int]) -> PinholeCamera:
        """The camera of photo ``name`` scaled to ``size_wh`` (the frame as captured); an :class:`InputError`
        when the file has none for it or its shape differs from the photo's."""
        camera = self.shared or dict(self.per_image).get(name)
        if camera is None:
            raise InputError(f"--intrinsics {self.path} has no camera for {name}", f"add a line for {name}: {FIX}")
        sx, sy = size_wh[0] / camera.width, size_wh[1] / camera.height
        if abs(sx - sy) > 0.01 * max(sx, sy):
            raise InputError(
                f"--intrinsics {self.path}: the camera of {name} is {camera.width}x{camera.height}, the photo "
                f"{size_wh[0]}x{size_wh[1]} (another shape)",
                "give the intrinsics of the photos as they are (upright, after EXIF orientation)",
            )
        return camera if (sx, sy) == (1.0, 1.0) else camera.scaled(sx, sy)


def _camera(tokens: list[str], where: str) -> PinholeCamera:
    model = tokens[1].upper()
    if model not in _MODELS:
        raise InputError(f"{where}: camera model {tokens[1]} is not one ffrecon takes", f"use one of {list(_MODELS)}")
    count, fx, fy, cx, cy, lens = _MODELS[model]
    try:
        width, height = int(tokens[2]), int(tokens[3])
        params = [float(t) for t in tokens[4:]]
    except (ValueError, IndexError):
        raise InputError(f"{where}: WIDTH HEIGHT and the parameters must be numbers", FIX) from None
    if len(params) != count:
        raise InputError(f"{where}: {model} takes {count} parameters, the line has {len(params)}", FIX)
    if any(params[lens:]):
        raise InputError(
            f"{where}: the lens has distortion ({model} {params[lens:]}); known distortion is not taken yet",
            "undistort the photos (colmap image_undistorter) and give their pinhole camera",
        )
    values = [params[fx], params[fy], params[cx], params[cy]]
    if min(width, height) < 1 or not all(v > 0 for v in values) or not all(abs(v) < 1e7 for v in values):
        raise InputError(f"{where}: a size or parameter is not a positive, finite number", FIX)
    return PinholeCamera(width, height, *values)


def read_intrinsics(path: Path) -> KnownIntrinsics:
    """Parse ``path`` (see the module's docstring); an :class:`InputError` naming the line that is wrong."""
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"--intrinsics {path} cannot be read ({err})", "pass a cameras.txt-style text file") from None
    rows = [(k + 1, line.split()) for k, line in enumerate(lines) if line.strip() and not line.lstrip().startswith("#")]
    if not rows:
        raise InputError(f"--intrinsics {path} holds no camera", FIX)
    cameras = [(tokens[0], _camera(tokens, f"--intrinsics {path}, line {k}")) for k, tokens in rows]
    by_id = [key.isdigit() for key, _ in cameras]
    if all(by_id) and len(cameras) == 1:
        return KnownIntrinsics(path, cameras[0][1])
    if any(by_id):
        raise InputError(
            f"--intrinsics {path}: {len(cameras)} cameras by id, and nothing says which photo has which",
            "give one camera for all photos, or name each photo in place of the id",
        )
    return KnownIntrinsics(path, None, tuple(cameras))
