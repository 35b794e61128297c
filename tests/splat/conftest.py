"""Splat tests run torch on one thread (see ``one_torch_thread`` in tests/conftest.py); a small scene with
its seed cloud for the stage tests."""

import numpy as np
import pytest

from ffrecon.splat.stage import split_views
from ffrecon.synthetic import SceneOptions, make_scene


@pytest.fixture(autouse=True)
def _one_thread(one_torch_thread):
    yield


def seeded_scene(width: int, height: int):
    """``(scene, xyz, rgb)``: 9 synthetic frames and the exact points and colours of the training views
    (every 8th frame held out, as the stage splits them)."""
    scene = make_scene(SceneOptions(num_frames=9, width=width, height=height))
    train, _ = split_views(len(scene), 8)
    xyz = np.concatenate([scene.frame_points(i).reshape(-1, 3) for i in train])
    rgb = np.concatenate([scene.images[i].reshape(-1, 3) for i in train]).astype(np.float32) / 255.0
    return scene, xyz, rgb
