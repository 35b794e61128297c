"""Seeding: point maps, sparse models, nearest-neighbour scales, downsampling."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from ffrecon.gaussians import SH_C0
from ffrecon.splat.seed import (
    initial_gaussians,
    nearest_neighbour_log_scales,
    reduce_points,
    seed_from_prediction,
    seed_from_reconstruction,
)
from ffrecon.synthetic import SceneOptions, make_scene
from ffrecon.types import ModelFamily, ModelInfo, Prediction


@pytest.fixture(scope="module")
def scene():
    return make_scene(SceneOptions(num_frames=3, width=64, height=48))


def _prediction(scene, conf: list[float], frames: list[int]) -> Prediction:
    return Prediction(
        names=tuple(scene.names[i] for i in frames),
        cam_from_world=scene.cam_from_world[frames],
        cameras=tuple(scene.camera for _ in frames),
        depth=tuple(scene.depth[i] for i in frames),
        depth_conf=tuple(np.full(scene.depth[i].shape, conf[k], np.float32) for k, i in enumerate(frames)),
        model=ModelInfo("test", ModelFamily.MULTIVIEW, simulated=True),
    )


def test_seed_from_prediction_filters_confidence_and_lies_on_the_surfaces(scene):
    voxel = 0.02
    pred = _prediction(scene, [2.0, 0.5, 0.5], [0, 1, 2])  # frames 1 and 2 are below min_conf
    xyz, rgb = seed_from_prediction(pred, list(scene.images), min_conf=1.0, voxel_size=voxel, max_points=10**6)
    only_first = seed_from_prediction(
        _prediction(scene, [2.0], [0]), [scene.images[0]], min_conf=1.0, voxel_size=voxel, max_points=10**6
    )
    assert np.array_equal(xyz, only_first[0]) and np.array_equal(rgb, only_first[1])
    confident = _prediction(scene, [2.0, 2.0, 2.0], [0, 1, 2])
    assert np.array_equal(
        seed_from_prediction(confident, list(scene.images), voxel_size=voxel, max_points=10**6, frames=[0])[0], xyz
    )
    truth = scene.frame_points(0).reshape(-1, 3)
    nearest = np.min(np.linalg.norm(xyz[:, None, :] - truth[None], axis=2), axis=1)
    assert np.percentile(nearest, 95) < voxel * np.sqrt(3)
    assert rgb.dtype == np.float32 and rgb.min() >= 0 and rgb.max() <= 1
    capped = seed_from_prediction(pred, list(scene.images), min_conf=0.0, max_points=500)[0]
    assert 400 <= len(capped) <= 500


def test_seed_from_reconstruction():
    rec = pycolmap.Reconstruction()
    pts = np.array([[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]])
    for p, c in zip(pts, [[255, 0, 0], [0, 128, 255]]):
        rec.add_point3D(p, pycolmap.Track(), np.array(c, np.uint8))
    xyz, rgb = seed_from_reconstruction(rec)
    order = np.argsort(xyz[:, 0])
    assert np.allclose(xyz[order], pts) and np.allclose(rgb[order], np.array([[1, 0, 0], [0, 128 / 255, 1]]))


def test_nearest_neighbour_scales_match_brute_force():
    rng = np.random.default_rng(0)
    xyz = rng.uniform(size=(300, 3))
    dist = np.linalg.norm(xyz[:, None] - xyz[None], axis=2)
    np.fill_diagonal(dist, np.inf)
    expected = np.log(np.sort(dist, axis=1)[:, :3].mean(1))
    assert np.allclose(nearest_neighbour_log_scales(xyz), expected, atol=1e-5)
    g = initial_gaussians(xyz, np.full((300, 3), 0.75), sh_degree=2, opacity=0.1)
    assert (
        g.sh.shape == (300, 9, 3)
        and np.allclose(g.sh[:, 0].numpy(), 0.25 / SH_C0)
        and float(g.sh[:, 1:].abs().max()) == 0
    )
    assert np.allclose(g.log_scales[:, 0].numpy(), expected, atol=1e-5) and np.allclose(
        g.log_scales[:, 1].numpy(), g.log_scales[:, 2].numpy()
    )
    assert np.allclose(g.quats_wxyz.numpy(), [1, 0, 0, 0]) and np.allclose(
        1 / (1 + np.exp(-g.opacity_logits.numpy())), 0.1
    )


def test_reduce_points_is_deterministic_and_capped():
    rng = np.random.default_rng(1)
    xyz = rng.normal(size=(20000, 3))
    xyz /= np.linalg.norm(xyz, axis=1, keepdims=True)  # a surface, as point maps are
    rgb = rng.uniform(size=(20000, 3)).astype(np.float32)
    a = reduce_points(xyz, rgb, voxel_size=None, max_points=3000, seed=3)
    b = reduce_points(xyz, rgb, voxel_size=None, max_points=3000, seed=3)
    assert np.array_equal(a[0], b[0]) and 0.85 * 3000 <= len(a[0]) <= 3000
