"""nerfstudio's camera_path.json: written and read back, loaded by nerfstudio's own loader (its pinned copy in
clients/python, in a subprocess), and every bad file refused with one InputError naming the problem."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ffrecon.errors import InputError
from ffrecon.formats.camera_path import (
    CameraPath,
    cam_from_world_from_opengl,
    read_camera_path,
    vertical_fov_deg,
    write_camera_path,
)
from ffrecon.formats.nerfstudio import world_from_cam_opengl
from ffrecon.geometry.poses import camera_centers, look_at_cam_from_world
from ffrecon.splat.video import flythrough_path, path_frames
from ffrecon.types import PinholeCamera

ROOT = Path(__file__).resolve().parents[2]
NERFSTUDIO = ROOT / "clients" / "python"  # nerfstudio and what its loaders import (make clients)
CAMERA = PinholeCamera(161, 121, 150.0, 152.0, 80.0, 61.0)  # odd sides: the path crops them to even


def _ring(n: int = 6) -> np.ndarray:
    angles = np.linspace(0, 2, n)
    centers = np.stack([3 * np.cos(angles), 3 * np.sin(angles), np.full(n, 1.0)], axis=1)
    return np.stack([look_at_cam_from_world(c, np.zeros(3)) for c in centers])


@pytest.fixture
def path_file(tmp_path) -> tuple[Path, CameraPath]:
    fly = flythrough_path(_ring(), CAMERA, num_frames=20, fps=24.0)
    return write_camera_path(tmp_path / "camera_path.json", fly), fly


def test_the_opengl_conversion_is_transforms_json_s(path_file):
    """camera_to_world is world_from_cam with the y and z axes flipped: the camera looks down its -z, and the
    position is the camera centre."""
    file, fly = path_file
    data = json.loads(file.read_text())
    c2w = np.array(data["camera_path"][0]["camera_to_world"]).reshape(4, 4)
    assert np.allclose(c2w, world_from_cam_opengl(fly.cam_from_world[:1])[0])
    assert np.allclose(c2w[:3, 3], camera_centers(fly.cam_from_world[:1])[0])
    forward_cv = fly.cam_from_world[0, 2, :3]  # OpenCV +z in the world
    assert np.allclose(-c2w[:3, 2], forward_cv)
    assert np.allclose(cam_from_world_from_opengl(c2w[None])[0], fly.cam_from_world[0])


def test_written_path_reads_back(path_file):
    file, fly = path_file
    back = read_camera_path(file)
    assert (back.width, back.height, back.fps) == (160, 120, 24.0) and back.seconds == pytest.approx(20 / 24)
    assert np.allclose(back.cam_from_world, fly.cam_from_world, atol=1e-12)
    assert np.allclose(back.keyframes, _ring(), atol=1e-12)
    assert np.allclose(back.fov_deg, vertical_fov_deg(PinholeCamera(160, 120, 150.0, 152.0, 80.0, 60.0)))
    camera = back.camera(float(back.fov_deg[0]))
    assert camera.fy == pytest.approx(152.0) and camera.fx == camera.fy and (camera.cx, camera.cy) == (80.0, 60.0)
    data = json.loads(file.read_text())
    assert len(data["keyframes"]) == 6 and len(data["camera_path"]) == 20 and data["camera_type"] == "perspective"
    assert data["frame"] == "sparse/0" and data["keyframes"][0]["aspect"] == pytest.approx(160 / 120)


_LOAD = """
import json, sys
from nerfstudio.cameras.camera_paths import get_path_from_json
cams = get_path_from_json(json.load(open(sys.argv[1])))
print(json.dumps({"c2w": cams.camera_to_worlds.double().tolist(), "fx": cams.fx.flatten().tolist(),
    "fy": cams.fy.flatten().tolist(), "cx": cams.cx.flatten().tolist(), "cy": cams.cy.flatten().tolist(),
    "w": cams.width.flatten().tolist(), "h": cams.height.flatten().tolist()}))
"""


def test_nerfstudio_s_loader_reads_our_cameras(path_file):
    """nerfstudio's ``get_path_from_json`` (what ``ns-render camera-path`` calls) gives our frames' cameras:
    the same poses (float32) and the same pinhole intrinsics."""
    if not (NERFSTUDIO / "nerfstudio").is_dir():
        pytest.skip("nerfstudio is not installed: `make clients` installs it into clients/python")
    file, fly = path_file
    env = {**os.environ, "PYTHONPATH": str(NERFSTUDIO)}
    done = subprocess.run([sys.executable, "-c", _LOAD, str(file)], capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stderr[-3000:]
    got = json.loads(done.stdout.strip().splitlines()[-1])
    cam_from_world = cam_from_world_from_opengl(
        np.concatenate([np.array(got["c2w"]), np.tile([[[0, 0, 0, 1.0]]], (20, 1, 1))], axis=1)
    )
    assert np.allclose(cam_from_world, fly.cam_from_world, atol=1e-5)
    camera = fly.camera(float(fly.fov_deg[0]))
    assert np.allclose(got["fx"], camera.fx, rtol=1e-6) and np.allclose(got["fy"], camera.fy, rtol=1e-6)
    assert np.allclose(got["cx"], camera.cx) and np.allclose(got["cy"], camera.cy)
    assert set(got["w"]) == {160} and set(got["h"]) == {120}


def test_keyframes_only_are_interpolated_through_each_keyframe(path_file):
    file, _ = path_file
    data = json.loads(file.read_text())
    del data["camera_path"]
    data["seconds"], data["fps"] = 2.0, 10
    file.write_text(json.dumps(data))
    path = read_camera_path(file)
    assert path.cam_from_world is None
    poses, fov = path_frames(path)
    assert len(poses) == len(fov) == 20
    assert np.allclose(poses[0], _ring()[0], atol=1e-9) and np.allclose(poses[-1], _ring()[-1], atol=1e-9)


def _bad(data: dict, case: str) -> dict | str:
    """``data`` spoiled as ``case`` says."""
    matrix = data["camera_path"][0]["camera_to_world"]
    spoil = {
        "not JSON": lambda d: "{'keyframes': [",
        "a list": lambda d: "[1, 2]",
        "no keyframes": lambda d: {k: v for k, v in d.items() if k != "keyframes"},
        "empty keyframes": lambda d: {**d, "keyframes": []},
        "matrix of 12": lambda d: {**d, "camera_path": [{**d["camera_path"][0], "camera_to_world": matrix[:12]}]},
        "matrix with text": lambda d: {**d, "keyframes": [{**d["keyframes"][0], "matrix": ["1"] * 16}]},
        "scaled matrix": lambda d: {
            **d,
            "camera_path": [{**d["camera_path"][0], "camera_to_world": list(np.diag([2.0, 2, 2, 1]).flatten())}],
        },
        "nan fov": lambda d: {**d, "camera_path": [{**d["camera_path"][0], "fov": float("nan")}]},
        "zero height": lambda d: {**d, "render_height": 0},
        "fisheye": lambda d: {**d, "camera_type": "fisheye"},
        "other frame": lambda d: {**d, "frame": "nerfstudio"},
        "no fps": lambda d: {k: v for k, v in d.items() if k != "fps"},
    }
    return spoil[case](data)


BAD = {
    "not JSON": "is not JSON",
    "a list": "not an object",
    "no keyframes": "has no keyframes",
    "empty keyframes": "has no keyframes",
    "matrix of 12": "camera_path[0].camera_to_world is not 16 finite numbers (12 values)",
    "matrix with text": "keyframes[0].matrix is not 16 finite numbers",
    "scaled matrix": "camera_path[0].camera_to_world is not a rigid",
    "nan fov": "camera_path[0].fov is nan",
    "zero height": "render_height is 0",
    "fisheye": "of type 'fisheye'",
    "other frame": "in frame 'nerfstudio'",
    "no fps": "fps is None",
}


@pytest.mark.parametrize("case", list(BAD))
def test_a_bad_path_file_is_an_input_error_naming_the_problem(path_file, case):
    file, _ = path_file
    spoiled = _bad(json.loads(file.read_text()), case)
    file.write_text(spoiled if isinstance(spoiled, str) else json.dumps(spoiled))
    with pytest.raises(InputError) as err:
        read_camera_path(file)
    assert BAD[case] in err.value.problem and str(file) in err.value.problem
    assert err.value.fix


def test_a_missing_path_file_says_so(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        read_camera_path(tmp_path / "nope.json")
