"""Known intrinsics the user gives (``--intrinsics FILE``), in COLMAP's ``cameras.txt`` form.

Either one camera for every photo (a ``cameras.txt`` with one line: ``CAMERA_ID MODEL WIDTH HEIGHT
PARAMS...``), or one per photo (the photo's file name in place of the id: ``NAME MODEL WIDTH HEIGHT
PARAMS...``). Models: ``SIMPLE_PINHOLE`` (f, cx, cy), ``PINHOLE`` (fx, fy, cx, cy), and the lens models
``SIMPLE_RADIAL`` (f, cx, cy, k), ``RADIAL`` (f, cx, cy, k1, k2), ``OPENCV`` (fx, fy, cx, cy, k1, k2, p1,
p2) and ``OPENCV_FISHEYE`` (fx, fy, cx, cy, k1..k4): the capture undistorts photos with a lens to pinhole
frames of the same K (:func:`ffrecon.capture.lens.undistort_lens`). Values are in the pixels of the given
``WIDTH x HEIGHT`` and follow COLMAP's pixel-centre rule; they are scaled to each frame as captured.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ffrecon.checks import MB, read_option_text
from ffrecon.errors import InputError
from ffrecon.types import PinholeCamera

# model -> (number of parameters, index of fx, fy, cx, cy, first distortion parameter)
_MODELS = {
    "SIMPLE_PINHOLE": (3, 0, 0, 1, 2, 3),
    "PINHOLE": (4, 0, 1, 2, 3, 4),
    "SIMPLE_RADIAL": (4, 0, 0, 1, 2, 3),
    "RADIAL": (5, 0, 0, 1, 2, 3),
    "OPENCV": (8, 0, 1, 2, 3, 4),
    "OPENCV_FISHEYE": (8, 0, 1, 2, 3, 4),  # k1..k4 of OpenCV's fisheye model
}
Lens = tuple[str, tuple[float, float, float, float]]  # ("fisheye", k1..k4) or ("opencv", (k1, k2, p1, p2))


def _lens(model: str, coefficients: list[float]) -> Lens | None:
    """The lens of a camera line: OpenCV's fisheye model (a fisheye even with k1..k4 = 0: an equidistant lens)
    or its radial-tangential one; None for a pinhole (no distortion)."""
    if model == "OPENCV_FISHEYE":
        return "fisheye", tuple(coefficients)
    if not any(coefficients):
        return None
    padded = (coefficients + [0.0, 0.0, 0.0, 0.0])[:4]  # SIMPLE_RADIAL (k), RADIAL (k1, k2), OPENCV (k1, k2, p1, p2)
    return "opencv", (padded[0], padded[1], padded[2], padded[3])


LIMIT_BYTES = 16 * MB  # a line per photo is ~100 bytes: 160,000 photos
FIX = "write one line per camera as in COLMAP's cameras.txt: ID (or the photo's name) MODEL WIDTH HEIGHT PARAMS"


@dataclass(frozen=True)
class KnownIntrinsics:
    """The cameras of ``path``: ``shared`` for every photo, or ``per_image`` by photo name."""

    path: Path
    shared: PinholeCamera | None
    per_image: tuple[tuple[str, PinholeCamera], ...] = ()
    # Lenses with distortion by photo name ("" for the shared camera); the camera is then the lens's fx, fy, cx, cy.
    lenses: tuple[tuple[str, Lens], ...] = ()

    def lens_of(self, name: str) -> Lens | None:
        """The lens of photo ``name``, None for a pinhole."""
        lenses = dict(self.lenses)
        return lenses.get("") if self.shared is not None else lenses.get(name)

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


def _camera(tokens: list[str], where: str) -> tuple[PinholeCamera, Lens | None]:
    if len(tokens) < 5:
        raise InputError(f"{where}: {len(tokens)} fields, a camera line has ID MODEL WIDTH HEIGHT PARAMS", FIX)
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
    values = [params[fx], params[fy], params[cx], params[cy]]
    if (
        not 1 <= min(width, height) <= max(width, height) < 10**6
        or not all(v > 0 for v in values)
        or not all(abs(v) < 1e7 for v in values)
    ):
        raise InputError(f"{where}: a size or parameter is not a positive, finite number", FIX)
    return PinholeCamera(width, height, *values), _lens(model, params[lens:])


def read_intrinsics(path: Path) -> KnownIntrinsics:
    """Parse ``path`` (see the module's docstring); an :class:`InputError` naming the line that is wrong."""
    path = Path(path)
    lines = read_option_text("--intrinsics", path, limit_bytes=LIMIT_BYTES, fix=FIX).splitlines()
    rows = [(k + 1, line.split()) for k, line in enumerate(lines) if line.strip() and not line.lstrip().startswith("#")]
    if not rows:
        raise InputError(f"--intrinsics {path} holds no camera", FIX)
    parsed = [(tokens[0], *_camera(tokens, f"--intrinsics {path}, line {k}")) for k, tokens in rows]
    cameras = [(key, camera) for key, camera, _ in parsed]
    by_id = [key.isdigit() for key, _ in cameras]
    if all(by_id) and len(cameras) == 1:
        lens = parsed[0][2]
        return KnownIntrinsics(path, cameras[0][1], lenses=(("", lens),) if lens is not None else ())
    if any(by_id):
        raise InputError(
            f"--intrinsics {path}: {len(cameras)} cameras by id, and nothing says which photo has which",
            "give one camera for all photos, or name each photo in place of the id",
        )
    lenses = tuple((key, lens) for key, _, lens in parsed if lens is not None)
    return KnownIntrinsics(path, None, tuple(cameras), lenses=lenses)
