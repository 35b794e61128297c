"""ffrecon's output folder in the clients people use: nerfstudio's own data parsers and COLMAP's command line.

Both must read the final cameras (``sparse/0``), not the cross-check: nerfstudio's ``nerfstudio`` parser from
``transforms.json`` and its ``colmap`` parser from ``colmap/sparse/0``, each with a dataparser transform that
maps its cameras and points back onto ffrecon's; COLMAP's ``model_analyzer`` and ``image_undistorter`` on
``sparse/0``. nerfstudio runs in a subprocess from ``clients/python`` (``make clients`` installs it, pinned);
COLMAP is Debian's ``colmap``. Each test is skipped, with the reason, when its client is missing.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import open3d as o3d
import pycolmap
import pytest

from ffrecon.colmap_io import cam_from_world_by_name

ROOT = Path(__file__).resolve().parents[2]
NERFSTUDIO = ROOT / "clients" / "python"  # nerfstudio and what its data parsers import (make clients)
PROBE = Path(__file__).with_name("nerfstudio_probe.py")
# nerfstudio holds cameras and points in float32: 1e-6 relative to the scene (positions of a few units).
POSE_TOL = 1e-5
OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0])


@pytest.fixture(scope="module")
def no_model_run(tmp_path_factory, demo12) -> Path:
    """COLMAP's cameras as the final ones: a SIMPLE_RADIAL lens with k1 (OPENCV in transforms.json)."""
    from ffrecon.pipeline import RunOptions, run
    from ffrecon.splat.stage import SplatOptions

    out = tmp_path_factory.mktemp("no-model") / "out"
    assert run(demo12.images, out, None, RunOptions(splat=SplatOptions(enabled=False))).exit_code == 0
    return out


@pytest.fixture(scope="module", params=["full_run", "no_model_run"])
def folder(request) -> Path:
    """An output folder: the model's refined cameras (pinhole), or COLMAP's (with a radial lens)."""
    return request.getfixturevalue(request.param)


@pytest.fixture(scope="module")
def nerfstudio_outputs(folder) -> dict:
    if not (NERFSTUDIO / "nerfstudio").is_dir():
        pytest.skip("nerfstudio is not installed: `make clients` installs it into clients/python")
    env = {**os.environ, "PYTHONPATH": str(NERFSTUDIO)}
    done = subprocess.run(
        [sys.executable, str(PROBE), str(folder)], capture_output=True, text=True, env=env, timeout=600
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def _final(run_dir: Path) -> tuple[pycolmap.Reconstruction, list[str]]:
    rec = pycolmap.Reconstruction(str(run_dir / "sparse" / "0"))
    return rec, sorted(im.name for im in rec.images.values())


def _mapped_back(parsed: dict) -> tuple[np.ndarray, np.ndarray | None]:
    """``(cam_from_world [N, 3, 4] OpenCV, points [M, 3] or None)`` in the world the folder was written in:
    the parser's cameras and points with its dataparser transform and scale undone."""
    transform = np.vstack([np.array(parsed["transform"]), [0, 0, 0, 1]])
    back = np.linalg.inv(transform)
    c2w = np.array(parsed["camera_to_worlds"])  # [N, 3, 4] OpenGL, transformed, positions scaled
    c2w[:, :, 3] /= parsed["scale"]
    c2w = np.einsum("ij,njk->nik", back[:3, :3], c2w)
    c2w[:, :, 3] += back[:3, 3]
    rot = c2w[:, :, :3] @ OPENGL_FROM_OPENCV
    cam_from_world = np.concatenate([rot.transpose(0, 2, 1), -rot.transpose(0, 2, 1) @ c2w[:, :, 3:]], axis=2)
    points = None
    if parsed["points"] is not None:
        p = np.array(parsed["points"]) / parsed["scale"]
        points = p @ back[:3, :3].T + back[:3, 3]
    return cam_from_world, points


@pytest.mark.parametrize("parser", ["nerfstudio", "colmap"])
def test_nerfstudio_parsers_read_the_final_cameras_and_map_back(nerfstudio_outputs, folder, parser):
    rec, names = _final(folder)
    parsed = nerfstudio_outputs[parser]
    assert parsed["files"] == names
    cam_from_world, points = _mapped_back(parsed)
    truth, _ = cam_from_world_by_name(rec, names)
    np.testing.assert_allclose(cam_from_world, truth, atol=POSE_TOL)
    for k, name in enumerate(names):  # intrinsics and lens: the final camera of each frame
        cam = rec.cameras[rec.find_image_with_name(name).camera_id]
        fx, fy, cx, cy = cam.calibration_matrix()[[0, 1, 0, 1], [0, 1, 2, 2]]
        got = [parsed[key][k] for key in ("fx", "fy", "cx", "cy")]
        np.testing.assert_allclose(got, [fx, fy, cx, cy], rtol=1e-6)
        k1 = cam.params[3] if cam.model.name in ("SIMPLE_RADIAL", "RADIAL") else 0.0
        np.testing.assert_allclose(parsed["distortion"][k][0], k1, rtol=1e-6)  # nerfstudio: [k1, k2, k3, k4, p1, p2]
    if parser == "nerfstudio":  # transforms.json's ply_file_path: points.ply
        truth_points = np.asarray(o3d.io.read_point_cloud(str(folder / "points.ply")).points)
    else:  # colmap/sparse/0's points, which are sparse/0's
        truth_points = np.array([p.xyz for p in rec.points3D.values()])
    assert points is not None and len(points) == len(truth_points)
    np.testing.assert_allclose(np.sort(points, axis=0), np.sort(truth_points, axis=0), atol=POSE_TOL)


def _colmap() -> str:
    path = shutil.which("colmap")
    if path is None:
        pytest.skip("COLMAP's command line is not installed: `make clients` installs Debian's colmap")
    done = subprocess.run([path, "help"], capture_output=True, text=True, timeout=60)
    if done.returncode != 0:
        pytest.skip(f"Debian's colmap does not start here: {(done.stderr or done.stdout).strip()[:200]}")
    return path


def test_colmap_cli_analyses_and_undistorts_the_final_model(folder, tmp_path):
    colmap = _colmap()
    rec, names = _final(folder)
    analysed = subprocess.run(
        [colmap, "model_analyzer", "--path", str(folder / "sparse" / "0")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    text = analysed.stdout + analysed.stderr
    assert analysed.returncode == 0, text
    registered = int(re.search(r"Registered images:\s*(\d+)", text).group(1))
    error = float(re.search(r"Mean reprojection error:\s*([\d.]+)px", text).group(1))
    assert registered == len(names) == rec.num_reg_images()
    assert error == pytest.approx(rec.compute_mean_reprojection_error(), abs=1e-3)
    out = tmp_path / "undistorted"
    undistort = [colmap, "image_undistorter", "--image_path", str(folder / "images")]
    undistort += ["--input_path", str(folder / "sparse" / "0"), "--output_path", str(out)]
    done = subprocess.run(undistort, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    undistorted = pycolmap.Reconstruction(str(out / "sparse"))
    poses, registered_mask = cam_from_world_by_name(undistorted, names)
    truth, _ = cam_from_world_by_name(rec, names)
    assert registered_mask.all() and len(list((out / "images").iterdir())) == len(names)
    np.testing.assert_allclose(poses, truth, atol=1e-9)
    assert all(not np.any(c.params[c.extra_params_idxs()]) for c in undistorted.cameras.values())  # no lens left
