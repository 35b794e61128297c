"""Validation helpers that raise typed, readable errors (never ``assert`` on user input)."""

from __future__ import annotations

import math
import os
import stat
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ffrecon.errors import InputError, ModelError, NonFiniteError, ShapeError


def check_shape(name: str, array: np.ndarray, expected: Sequence[int | None], *, fix: str = "") -> None:
    """Raise :class:`ShapeError` unless ``array.shape`` matches ``expected`` (``None`` = any size); ``fix``:
    what the caller should do, which the calling stage knows.

    >>> check_shape("points", np.zeros((5, 3)), (None, 3))
    >>> check_shape("points", np.zeros((5, 2)), (None, 3), fix="pass [N, 3] points")
    Traceback (most recent call last):
    ...
    ffrecon.errors.ShapeError: points: expected shape (N, 3), got (5, 2)
      fix: pass [N, 3] points
    """
    shape = tuple(array.shape)
    ok = len(shape) == len(expected) and all(e is None or e == s for e, s in zip(expected, shape))
    if not ok:
        want = ", ".join("N" if e is None else str(e) for e in expected)
        raise ShapeError(f"{name}: expected shape ({want}), got {shape}", fix)


def require_outputs(outputs, required: Sequence[str], *, fix: str) -> None:
    """Raise :class:`ModelError` naming the required model outputs that are missing.

    >>> require_outputs({"depth": 1}, ("depth",), fix="")
    >>> require_outputs({"depth": 1}, ("depth", "pose_enc"), fix="re-export")
    Traceback (most recent call last):
    ...
    ffrecon.errors.ModelError: model outputs lack ['pose_enc']; got ['depth']
      fix: re-export
    """
    missing = [k for k in required if k not in outputs]
    if missing:
        raise ModelError(f"model outputs lack {missing}; got {sorted(outputs)}", fix)


def strip_batch_axis(name: str, array: np.ndarray, shape: Sequence[int | None], *, fix: str) -> np.ndarray:
    """A model output without its optional leading batch axis of 1, checked against ``shape`` (None: any size).

    >>> strip_batch_axis("depth", np.zeros((1, 2, 4, 5)), (None, None, None), fix="").shape
    (2, 4, 5)
    >>> strip_batch_axis("depth", np.zeros((2, 4)), (None, None, None), fix="re-export")
    Traceback (most recent call last):
    ...
    ffrecon.errors.ModelError: model output 'depth' has shape [2, 4]; expected [1, ?, ?, ?] (the leading 1 optional)
      fix: re-export
    """
    array = np.asarray(array)
    if array.ndim == len(shape) + 1 and array.shape[0] == 1:
        array = array[0]
    if array.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, array.shape)):
        want = "[1, " + ", ".join("?" if s is None else str(s) for s in shape) + "]"
        raise ModelError(
            f"model output '{name}' has shape {list(array.shape)}; expected {want} (the leading 1 optional)", fix
        )
    return array


def require_finite(step: str, *, fix: str = "", **arrays: np.ndarray) -> None:
    """Refuse NaN/inf inputs to an iterative or linear-algebra step (they can make LAPACK spin forever) with a
    :class:`NonFiniteError`. ``fix``: where the values came from is the caller's knowledge, so is the fix (a
    kernel that does not know leaves it empty, and the stage that called it adds it: ``err.with_fix``).

    >>> require_finite("alignment", src=np.zeros((2, 3)))
    >>> require_finite("alignment", src=np.array([1.0, np.nan]), fix="re-export the model")
    Traceback (most recent call last):
    ...
    ffrecon.errors.NonFiniteError: alignment: input 'src' has 1 non-finite values (NaN/inf) of 2
      fix: re-export the model
    """
    for name, array in arrays.items():
        bad = ~np.isfinite(np.asarray(array, dtype=np.float64))
        if bad.any():
            raise NonFiniteError(
                f"{step}: input '{name}' has {int(bad.sum())} non-finite values (NaN/inf) of {bad.size}", fix
            )


def check_finite(name: str, array: np.ndarray, *, model: str = "") -> None:
    """Raise :class:`ModelError` if a model output holds NaN or infinite values."""
    bad = ~np.isfinite(array)
    if bad.any():
        raise ModelError(
            f"model output '{name}' has {int(bad.sum())} non-finite values (NaN/inf) of {array.size}"
            + (f" in {model}" if model else ""),
            "the ONNX export is probably broken (fp16 overflow is a common cause): re-export in fp32, "
            "or check the model on one image with `ffrecon inspect-model`",
        )


def check_number(
    name: str,
    value: float | int | None,
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    integer: bool = False,
    allow_none: bool = False,
    flag: str = "",
) -> None:
    """Raise :class:`InputError` unless ``value`` is a finite number in ``[low, high]`` (``(low, high]``
    with ``low_open``); ``integer`` also asks for a whole number. ``flag`` names the command-line option
    that sets it, so the CLI and the Python API give the same message.

    Option dataclasses call it from ``__post_init__``, so an option is checked where it is made.

    >>> check_number("splat max_seconds", 60.0, low=0.0, low_open=True)
    >>> check_number("splat max_seconds", float("nan"), low=0.0, low_open=True, flag="--splat-seconds")
    Traceback (most recent call last):
    ...
    ffrecon.errors.InputError: --splat-seconds (splat max_seconds) must be a finite number > 0; got nan
      fix: pass --splat-seconds with a finite number > 0
    """
    if value is None and allow_none:
        return
    label = f"{flag} ({name})" if flag else name
    want = "a whole number" if integer else "a finite number"
    bounds = []
    if low is not None:
        bounds.append(f"{'>' if low_open else '>='} {low:g}")
    if high is not None:
        bounds.append(f"<= {high:g}")
    want_text = f"{want} {' and '.join(bounds)}".strip()
    fix = f"pass {flag} with {want_text}" if flag else f"set {name} to {want_text}"
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
    if ok:
        ok = math.isfinite(float(value)) and (not integer or float(value) == int(value))
    if ok and low is not None:
        ok = float(value) > low if low_open else float(value) >= low
    if ok and high is not None:
        ok = float(value) <= high
    if not ok:
        raise InputError(f"{label} must be {want_text}; got {value!r}", fix)


# --- files the user names in an option (--intrinsics, --poses, --masks, --vocab-tree, --reference, ...) ----------

MB = 1 << 20
GB = 1 << 30


def _kind(mode: int) -> str:
    """What a file system entry is, in words ("a FIFO", "a character device", ...)."""
    kinds = (
        (stat.S_ISREG, "a regular file"),
        (stat.S_ISDIR, "a folder"),
        (stat.S_ISFIFO, "a FIFO (named pipe)"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
    )
    return next((words for test, words in kinds if test(mode)), "not a regular file")


def check_option_folder(option: str, path: Path, *, fix: str) -> Path:
    """``path`` when it is a folder (a link to one counts); else an :class:`InputError` naming ``option``,
    the path and what it is.

    >>> check_option_folder("--masks", Path("/"), fix="")
    PosixPath('/')
    >>> check_option_folder("--masks", Path("/dev/null"), fix="pass a folder of PNGs")
    Traceback (most recent call last):
    ...
    ffrecon.errors.InputError: --masks /dev/null is not a folder: it is a character device
      fix: pass a folder of PNGs
    """
    path = Path(path)
    if not Path(path).is_dir():
        raise InputError(f"{option} {path} is not a folder: {path_kind(path)}", fix)
    return path


def path_kind(path: Path) -> str:
    """What is at ``path``, in words, for messages.

    >>> path_kind(Path("/dev/null")), path_kind(Path("/does/not/exist"))
    ('it is a character device', 'it does not exist')
    """
    try:
        return f"it is {_kind(os.stat(path).st_mode)}"
    except OSError as err:
        return _reason(err)


def _reason(err: OSError) -> str:
    return "it does not exist" if isinstance(err, FileNotFoundError) else (err.strerror or str(err))


def read_option_bytes(option: str, path: Path, *, limit_bytes: int, fix: str) -> bytes:
    """The bytes of the file ``path`` that ``option`` names, read with a bound: an :class:`InputError` naming
    ``option``, the path and what it is when it is not a regular file (a FIFO, a device, a folder), is empty, or
    holds more than ``limit_bytes``. The file is opened without blocking and checked on the open descriptor,
    so a FIFO never hangs and a file swapped after a check is still caught.

    >>> read_option_bytes("--intrinsics", Path("/dev/zero"), limit_bytes=MB, fix="pass cameras.txt")
    Traceback (most recent call last):
    ...
    ffrecon.errors.InputError: --intrinsics /dev/zero is a character device, not a regular file
      fix: pass cameras.txt
    """
    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as err:
        raise InputError(f"{option} {path} cannot be read ({_reason(err)})", fix) from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise InputError(f"{option} {path} is {_kind(info.st_mode)}, not a regular file", fix)
        _check_size(option, path, info.st_size, limit_bytes, fix)
        with os.fdopen(fd, "rb", closefd=False) as file:
            data = file.read(limit_bytes + 1)
    except OSError as err:
        raise InputError(f"{option} {path} cannot be read ({_reason(err)})", fix) from None
    finally:
        os.close(fd)
    _check_size(option, path, len(data), limit_bytes, fix)  # it may have grown or shrunk since the fstat
    return data


def _check_size(option: str, path: Path, size: int, limit_bytes: int, fix: str) -> None:
    if size == 0:
        raise InputError(f"{option} {path} is empty", fix)
    if size > limit_bytes:
        raise InputError(
            f"{option} {path} is {_size_text(size)}, more than such a file can be ({_size_text(limit_bytes)})", fix
        )


def _size_text(size: int) -> str:
    """A size in bytes, MB or GB.

    >>> _size_text(3), _size_text(5 * MB), _size_text(20 * GB)
    ('3 bytes', '5.0 MB', '20.0 GB')
    """
    return f"{size / GB:.1f} GB" if size >= GB else f"{size / MB:.1f} MB" if size >= MB else f"{size} bytes"


def read_option_text(option: str, path: Path, *, limit_bytes: int, fix: str) -> str:
    """:func:`read_option_bytes` decoded as UTF-8 text; an :class:`InputError` for bytes that are not text."""
    data = read_option_bytes(option, path, limit_bytes=limit_bytes, fix=fix)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise InputError(f"{option} {path} is not text (byte {err.start} is not UTF-8)", fix) from None
    if "\x00" in text:
        raise InputError(f"{option} {path} is not text (it holds NUL bytes)", fix)
    return text


def check_option_file(option: str, path: Path, *, limit_bytes: int, fix: str) -> Path:
    """``path`` when it is a regular file of 1 to ``limit_bytes`` bytes, for a library that opens it itself
    (COLMAP); the same errors as :func:`read_option_bytes`, without reading it."""
    path = Path(path)
    try:
        info = os.stat(path)
    except OSError as err:
        raise InputError(f"{option} {path} cannot be read ({_reason(err)})", fix) from None
    if not stat.S_ISREG(info.st_mode):
        raise InputError(f"{option} {path} is {_kind(info.st_mode)}, not a regular file", fix)
    _check_size(option, path, info.st_size, limit_bytes, fix)
    return path


def check_model_files(option: str, folder: Path, *, limit_bytes: int, fix: str) -> None:
    """Each COLMAP model file in ``folder`` (cameras, images, points3D; .bin or .txt) that exists is a regular
    file of at most ``limit_bytes`` (see :func:`check_option_file`): checked before COLMAP opens them, where a FIFO
    would hang and a device would fill the memory."""
    for name in ("cameras", "images", "points3D", "rigs", "frames"):
        for found in (Path(folder) / f"{name}{suffix}" for suffix in (".bin", ".txt")):
            if os.path.lexists(found):
                check_option_file(option, found, limit_bytes=limit_bytes, fix=fix)
