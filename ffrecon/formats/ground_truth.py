"""``ground_truth.json`` of a synthetic scene folder (written by :func:`ffrecon.synthetic.write_scene`):
the scene's options, its camera (COLMAP's pixel convention) and each frame's name and ``cam_from_world``
(3x4, OpenCV). Read here without the images, for scoring a run against it."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ffrecon.checks import MB, read_option_text
from ffrecon.errors import InputError

FILE_NAME = "ground_truth.json"
LIMIT_BYTES = 256 * MB


def read_ground_truth(folder: Path) -> dict:
    """The parsed ``folder/ground_truth.json``; an :class:`InputError` when it is missing or unreadable."""
    path = Path(folder) / FILE_NAME
    fix = "pass the folder ffrecon.synthetic.write_scene wrote (it holds ground_truth.json)"
    if not os.path.lexists(path):
        raise InputError(f"no synthetic scene in {folder}: {FILE_NAME} is missing", fix)
    text = read_option_text("ground truth", path, limit_bytes=LIMIT_BYTES, fix=fix)
    try:
        truth = json.loads(text)
        [(f["name"], f["cam_from_world"]) for f in truth["frames"]]  # noqa: B018 (checks the fields are there)
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise InputError(f"{path} cannot be read as a synthetic scene's ground truth ({err})", fix) from None
    return truth


def ground_truth_poses(folder: Path) -> tuple[tuple[str, ...], np.ndarray]:
    """``(names, cam_from_world [N, 3, 4] float64)`` of the frames of a synthetic scene folder."""
    truth = read_ground_truth(folder)
    names = tuple(f["name"] for f in truth["frames"])
    poses = np.array([f["cam_from_world"] for f in truth["frames"]], dtype=np.float64).reshape(len(names), 3, 4)
    return names, poses
