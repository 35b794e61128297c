"""splat.ply layout and round trip, the fly-through video and the Poisson mesh."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
import trimesh
from plyfile import PlyData, PlyElement

from ffrecon.errors import InputError
from ffrecon.formats.mesh import poisson_mesh, write_mesh_files
from ffrecon.formats.splat_ply import read_splat_ply, splat_property_names, splat_to_array, write_splat_ply
from ffrecon.gaussians import Gaussians, rgb_to_sh_dc
from ffrecon.geometry.poses import camera_centers, look_at_cam_from_world
from ffrecon.geometry.rotations import rotation_angle_deg
from ffrecon.splat.render import render
from ffrecon.splat.video import smooth_camera_path, write_flythrough
from ffrecon.types import PinholeCamera

from .reference import random_scene

STANDARD_D3 = (
    ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    + [f"f_rest_{i}" for i in range(45)]
    + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
)


def _splat(rng: np.random.Generator, n: int = 50, degree: int = 3) -> tuple[Gaussians, torch.Tensor]:
    s = random_scene(rng, n, 48, 36, sh_bases=(degree + 1) ** 2)
    if degree == 0:
        s["colors"] = rgb_to_sh_dc(s["colors"])[:, None, :]
    g = Gaussians(
        *(
            torch.tensor(s[k], dtype=torch.float32)
            for k in ("means", "quats_wxyz", "log_scales", "opacity_logits", "colors")
        )
    )
    return g, torch.tensor(s["K"], dtype=torch.float32)


def test_property_list_is_the_standard_one():
    assert splat_property_names(3) == STANDARD_D3
    assert splat_property_names(1)[9:18] == [f"f_rest_{i}" for i in range(9)]


@pytest.mark.parametrize("degree", [0, 3])
def test_ply_round_trip(tmp_path, degree):
    rng = np.random.default_rng(degree)
    g, K = _splat(rng, degree=degree)
    path = write_splat_ply(tmp_path / "splat.ply", g)
    ply = PlyData.read(str(path))
    assert [e.name for e in ply.elements] == ["vertex"] and ply["vertex"].count == len(g)
    vertex = ply["vertex"].data
    assert list(vertex.dtype.names) == splat_property_names(degree)
    assert all(vertex.dtype[name] == np.dtype("<f4") for name in vertex.dtype.names)
    assert all(np.isfinite(vertex[name]).all() for name in vertex.dtype.names)
    # Values in the documented encodings: f_rest channel-major, rotation wxyz normalised.
    if degree:
        assert np.allclose(vertex["f_rest_0"], g.sh[:, 1, 0].numpy()) and np.allclose(
            vertex["f_rest_15"], g.sh[:, 1, 1].numpy()
        )
    q = torch.nn.functional.normalize(g.quats_wxyz, dim=1).numpy()
    assert np.allclose(np.stack([vertex[f"rot_{i}"] for i in range(4)], 1), q, atol=1e-6)
    back = read_splat_ply(path)
    pose = torch.eye(4)[:3]
    a = render(g.means, g.quats_wxyz, g.log_scales, g.opacity_logits, g.sh, pose, K, 48, 36, sh_degree=degree)
    b = render(
        back.means, back.quats_wxyz, back.log_scales, back.opacity_logits, back.sh, pose, K, 48, 36, sh_degree=degree
    )
    # 1e-5: the file stores unit quaternions in float32, which the projection renormalises in float64
    assert float((a.rgb - b.rgb).abs().max()) < 1e-5 and float(a.rgb.std()) > 0.01


def test_ply_pads_sh_degree(tmp_path):
    g, _ = _splat(np.random.default_rng(7), degree=0)
    back = read_splat_ply(write_splat_ply(tmp_path / "s.ply", g, sh_degree=3))
    assert back.sh.shape == (len(g), 16, 3) and float(back.sh[:, 1:].abs().max()) == 0.0
    assert torch.allclose(back.sh[:, 0], g.sh[:, 0])


def _orbit(n: int) -> np.ndarray:
    angles = np.linspace(0, np.pi, n)
    return np.stack(
        [look_at_cam_from_world(np.array([3 * np.cos(a), 3 * np.sin(a), 1.0]), np.zeros(3)) for a in angles]
    )


def test_smooth_path_passes_near_the_cameras_and_is_smooth():
    keys = _orbit(6)
    path = smooth_camera_path(keys, 51, smoothing=0.0)
    assert np.allclose(path[0], keys[0], atol=1e-9) and np.allclose(path[-1], keys[-1], atol=1e-9)
    assert np.allclose(path[10], keys[1], atol=1e-9)  # 51 frames over 5 segments: frame 10 is key 1
    centers = camera_centers(path)
    steps = np.linalg.norm(np.diff(centers, axis=0), axis=1)
    assert steps.max() < 1.5 * steps.mean()  # no jumps
    turn = rotation_angle_deg(np.swapaxes(path[1:, :, :3], 1, 2) @ path[:-1, :, :3])
    assert turn.max() < 5.0


def test_flythrough_video(tmp_path):
    g, K = _splat(np.random.default_rng(1), degree=0)
    g.means[:, 2] -= 3.0  # centre the random scene on the origin, seen by the orbit
    cam = PinholeCamera(48, 36, float(K[0, 0]), float(K[1, 1]), 24.0, 18.0)
    path = write_flythrough(tmp_path / "fly.mp4", g, _orbit(4), cam, num_frames=12)
    assert path is not None and path.stat().st_size > 0
    cap = cv2.VideoCapture(str(path))
    frames = 0
    while cap.read()[0]:
        frames += 1
    cap.release()
    assert frames == 12


def test_poisson_mesh_of_a_sphere(tmp_path):
    rng = np.random.default_rng(2)
    xyz = rng.normal(size=(6000, 3))
    xyz /= np.linalg.norm(xyz, axis=1, keepdims=True)
    rgb = np.tile([[0.8, 0.2, 0.1]], (len(xyz), 1))
    centers = np.array([[4.0, 0, 0], [-4.0, 0, 0], [0, 4.0, 0], [0, -4.0, 0], [0, 0, 4.0], [0, 0, -4.0]])
    ply, glb = write_mesh_files(poisson_mesh(xyz, rgb, centers), tmp_path / "mesh.ply", tmp_path / "mesh.glb")
    mesh = trimesh.load(glb, force="mesh")
    radius = np.linalg.norm(mesh.vertices, axis=1)
    assert len(mesh.faces) > 1000 and np.abs(radius - 1).max() < 0.05
    assert np.abs(mesh.visual.vertex_colors[:, :3].astype(float).mean(0) - [204, 51, 25]).max() < 10
    assert ply.stat().st_size > 0


def test_ply_from_another_writer_reads_and_a_bad_file_says_so(tmp_path):
    """Properties in another order with an extra one (as other tools write them) read back the same; a file
    that is not a splat PLY is an InputError naming the layout, not a traceback."""
    g, _ = _splat(np.random.default_rng(3), degree=1)
    arr, names = splat_to_array(g, 1), splat_property_names(1)
    order = ["x", "y", "z"] + [n for n in names if n not in ("x", "y", "z")][::-1] + ["extra"]
    rec = np.zeros(len(g), dtype=[(n, "<f4") for n in order])
    for i, n in enumerate(names):
        rec[n] = arr[:, i]
    PlyData([PlyElement.describe(rec, "vertex")]).write(str(tmp_path / "other.ply"))
    back = read_splat_ply(tmp_path / "other.ply")
    for key in ("means", "log_scales", "opacity_logits", "sh"):
        assert torch.allclose(getattr(back, key), getattr(g, key), atol=1e-6), key
    (tmp_path / "bad.ply").write_text("not a ply")
    with pytest.raises(InputError, match="3DGS"):
        read_splat_ply(tmp_path / "bad.ply")
