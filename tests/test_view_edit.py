"""``ffrecon view``'s editing tools, driven as the handles and buttons drive them: the crop box writes a cropped
splat with only the Gaussians inside it (splat.ply untouched) and a box file ``--crop-box`` reads; keyframes
from the browser's camera (viser's: OpenCV axes, world_from_cam) become a camera path ``ffrecon render``
renders."""

from __future__ import annotations

import socket
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from ffrecon import cli
from ffrecon.formats.camera_path import read_camera_path
from ffrecon.formats.splat_ply import read_splat_ply, write_splat_ply
from ffrecon.gaussians import Gaussians
from ffrecon.geometry.poses import invert_pose, look_at_cam_from_world
from ffrecon.geometry.rotations import matrix_to_quat_xyzw
from ffrecon.splat.clean import read_crop_box
from ffrecon.view import load_scene, start_viewer
from ffrecon.view.edit import CROP_BOX_FILE, CROPPED_PLY, CROPPED_SPZ, RECORDED_PATH


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def viewer(tmp_path):
    """A viewer of a folder with only a splat: 2000 Gaussians uniform in [-1, 1]^3."""
    rng = np.random.default_rng(0)
    means = rng.uniform(-1, 1, size=(2000, 3))
    g = Gaussians.from_points(means, np.full((2000, 3), 0.5), np.full(2000, np.log(0.02)), opacity=0.8)
    out = tmp_path / "out"
    write_splat_ply(out / "splat.ply", g)
    running = start_viewer(load_scene(out), port=_free_port())
    yield running
    running.stop()


def _viser_camera(cam_from_world: np.ndarray, fov_rad: float) -> SimpleNamespace:
    """What viser's ``client.camera`` says of an OpenCV camera: world_from_cam as wxyz and position."""
    world_from_cam = invert_pose(cam_from_world)
    x, y, z, w = matrix_to_quat_xyzw(world_from_cam[:, :3])
    return SimpleNamespace(wxyz=np.array([w, x, y, z]), position=world_from_cam[:, 3], fov=fov_rad)


def test_the_crop_box_writes_only_the_gaussians_inside_and_keeps_the_splat(viewer):
    out = Path(viewer.scene.out_dir)
    before = (out / "splat.ply").read_bytes()
    lo, hi = viewer.edit.lo, viewer.edit.hi
    assert np.all(lo < -0.99) and np.all(hi > 0.99)  # the box starts around the whole splat
    viewer.edit.set_box((-0.5, -0.2, 0.0), (0.5, 0.9, 0.4))
    assert viewer.edit.lo_field.value == (-0.5, -0.2, 0.0) and viewer.edit.hi_field.value == (0.5, 0.9, 0.4)
    done = viewer.edit.write_crop()
    assert done is not None and done.ply == out / CROPPED_PLY and (out / CROPPED_SPZ).stat().st_size > 0
    cropped = read_splat_ply(out / CROPPED_PLY).means.numpy()
    full = read_splat_ply(out / "splat.ply").means.numpy()
    inside = np.all((full >= [-0.5, -0.2, 0.0]) & (full <= [0.5, 0.9, 0.4]), axis=1)
    assert len(cropped) == inside.sum() == done.kept > 50 and done.total == 2000
    assert np.all(cropped >= np.array([-0.5, -0.2, 0.0]) - 1e-6) and np.all(cropped <= np.array([0.5, 0.9, 0.4]) + 1e-6)
    assert (out / "splat.ply").read_bytes() == before  # the uncropped splat is never lost
    assert read_crop_box(out / CROP_BOX_FILE) == ((-0.5, -0.2, 0.0), (0.5, 0.9, 0.4))
    args = cli.parse_args(["run", "photos", "-o", str(out.parent / "again"), "--crop-box", str(out / CROP_BOX_FILE)])
    assert args.crop_box == ((-0.5, -0.2, 0.0), (0.5, 0.9, 0.4))
    assert "splat_cropped.ply" in viewer.edit.crop_status.content


def test_dragging_a_handle_moves_the_box(viewer):
    edit = viewer.edit
    edit.set_box((0, 0, 0), (1, 1, 1))
    edit.handles["centre"].position = (1.0, 0.5, 0.5)  # the centre dragged 0.5 along x
    edit._dragged("centre")
    assert np.allclose(edit.lo, [0.5, 0, 0]) and np.allclose(edit.hi, [1.5, 1, 1])
    edit.handles["hi"].position = (2.0, 2.0, 0.2)  # the hi corner dragged below lo in z: the two swap
    edit._dragged("hi")
    assert np.allclose(edit.lo, [0.5, 0, 0]) and np.allclose(edit.hi, [2.0, 2.0, 0.2])
    assert np.allclose(edit.handles["lo"].position, edit.lo)


def test_an_empty_crop_is_said_and_writes_nothing(viewer):
    viewer.edit.set_box((5, 5, 5), (6, 6, 6))
    assert viewer.edit.write_crop() is None
    assert "no Gaussian" in viewer.edit.crop_status.content
    assert not (Path(viewer.scene.out_dir) / CROPPED_PLY).exists()


def test_keyframes_become_a_camera_path_that_renders(viewer, tmp_path, capsys):
    edit = viewer.edit
    assert edit.write_path() is None and "no keyframes" in edit.path_status.content
    angles = (0.0, 0.6, 1.2)
    keys = [look_at_cam_from_world(np.array([3 * np.cos(a), 3 * np.sin(a), 1.0]), np.zeros(3)) for a in angles]
    for pose in keys:
        edit.add_keyframe(_viser_camera(pose, np.radians(50.0)))
    edit.fps.value, edit.seconds.value = 5, 1.2
    written = edit.write_path()
    assert written == Path(viewer.scene.out_dir) / RECORDED_PATH
    path = read_camera_path(written)
    assert np.allclose(path.keyframes, np.stack(keys), atol=1e-9) and np.allclose(path.keyframe_fov_deg, 50.0)
    assert len(path.cam_from_world) == 6 and (path.width, path.height) == (1280, 720)
    assert np.allclose(path.cam_from_world[0], keys[0], atol=1e-9)
    assert np.allclose(path.cam_from_world[-1], keys[-1], atol=1e-9)
    video = tmp_path / "recorded.mp4"
    out = str(viewer.scene.out_dir)
    assert cli.main(["render", out, "--camera-path", str(written), "-o", str(video), "-q"]) == 0
    assert video.stat().st_size > 0
    edit.clear_keyframes()
    assert edit.recorder.cam_from_world == []
