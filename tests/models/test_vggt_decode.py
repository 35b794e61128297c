"""Exact decoding of VGGT-contract outputs back to original-photo cameras and depth."""

import numpy as np
import pytest

from ffrecon.errors import ModelError
from ffrecon.geometry.poses import compose_poses, invert_pose
from ffrecon.geometry.rotations import random_rotation
from ffrecon.models.vggt import ADAPTER, PreprocessMode, decode_vggt_outputs, encode_pose_enc, preprocess_vggt
from ffrecon.types import ModelFamily, ModelInfo

MODEL = ModelInfo("test", ModelFamily.MULTIVIEW)


def _ground_truth(width, height, n=4, seed=0):
    rng = np.random.default_rng(seed)
    rot = random_rotation(rng, n)
    cam_from_world = np.concatenate([rot, rng.normal(size=(n, 3, 1))], axis=2)
    # VGGT's world is the first camera: express everything relative to it.
    cam_from_world = compose_poses(cam_from_world, invert_pose(cam_from_world[0]))
    f = rng.uniform(0.7, 1.3, size=n) * max(width, height)
    K = np.zeros((n, 3, 3))
    K[:, 0, 0], K[:, 1, 1] = f, f * rng.uniform(0.98, 1.02, size=n)
    K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = width / 2, height / 2, 1
    return cam_from_world, K


def _outputs_from_truth(cam_from_world, K, transforms):
    """Network outputs a perfect model would give: K and depth in network pixels."""
    wn, hn = transforms[0].net_size_wh
    K_net = np.stack(
        [
            np.diag([t.scale_x, t.scale_y, 1.0]) @ k + np.array([[0, 0, t.offset_x], [0, 0, t.offset_y], [0, 0, 0]])
            for k, t in zip(K, transforms)
        ]
    )
    ys, xs = np.mgrid[0:hn, 0:wn] + 0.5
    depth = np.stack([2.0 + 0.001 * xs + 0.002 * ys + k for k in range(len(K))])  # planar in net pixels
    return {
        "pose_enc": encode_pose_enc(cam_from_world, K_net, (hn, wn))[None].astype(np.float32),
        "depth": depth[None, ..., None].astype(np.float32),
        "depth_conf": np.full((1,) + depth.shape, 2.0, np.float32),
    }, K_net


@pytest.mark.parametrize(
    "size_wh",
    [(320, 240), (240, 320), (1000, 750), (600, 900)],
    ids=["landscape", "portrait", "landscape-large", "portrait-large"],
)
@pytest.mark.parametrize("mode", list(ADAPTER.modes))
def test_decode_recovers_original_cameras(size_wh, mode):
    width, height = size_wh
    cam_from_world, K = _ground_truth(width, height)
    images = [np.zeros((height, width, 3), np.uint8)] * len(K)
    batch, transforms = preprocess_vggt(images, mode)
    assert batch.shape[2] % 14 == 0 and batch.shape[3] % 14 == 0
    assert (
        max(batch.shape[2:]) <= 518
        and (mode is PreprocessMode.CROP) == (batch.shape[3] == 518 and batch.shape[2] <= 518)
        or mode is PreprocessMode.PAD
    )
    outputs, K_net = _outputs_from_truth(cam_from_world, K, transforms)
    # The principal point of the ground truth lands exactly on the network image centre.
    np.testing.assert_allclose(K_net[:, :2, 2], [[batch.shape[3] / 2, batch.shape[2] / 2]] * len(K), atol=1e-9)
    pred = decode_vggt_outputs(outputs, transforms, [f"{k}.png" for k in range(len(K))], MODEL)
    np.testing.assert_allclose(pred.cam_from_world, cam_from_world, rtol=1e-4, atol=1e-5)
    for k, cam in enumerate(pred.cameras):
        assert (cam.width, cam.height) == (width, height)
        np.testing.assert_allclose(cam.K, K[k], rtol=1e-4)


@pytest.mark.parametrize("mode", list(ADAPTER.modes))
def test_depth_maps_back_to_original_pixels(mode):
    width, height = 240, 320  # portrait: crop mode cuts the top and bottom
    cam_from_world, K = _ground_truth(width, height, n=2)
    batch, transforms = preprocess_vggt([np.zeros((height, width, 3), np.uint8)] * 2, mode)
    outputs, _ = _outputs_from_truth(cam_from_world, K, transforms)
    pred = decode_vggt_outputs(outputs, transforms, ["a", "b"], MODEL)
    t = transforms[0]
    ys, xs = np.mgrid[0:height, 0:width] + 0.5
    xn, yn = xs * t.scale_x + t.offset_x, ys * t.scale_y + t.offset_y
    expected = 2.0 + 0.001 * xn + 0.002 * yn
    inside = (yn > 0.5) & (yn < t.net_size_wh[1] - 0.5) & (xn > 0.5) & (xn < t.net_size_wh[0] - 0.5)
    np.testing.assert_allclose(pred.depth[0][inside], expected[inside], rtol=1e-5)
    outside = (yn < -0.5) | (yn > t.net_size_wh[1] + 0.5)
    assert (mode is PreprocessMode.PAD) == (not outside.any())
    assert np.all(pred.depth[0][outside] == 0) and np.all(pred.depth_conf[0][outside] == 0)


def test_depth_grid_cap_keeps_geometry():
    """A capped depth grid samples the same surface: its pixel (i, j) is original point ((j+.5)f, (i+.5)f)."""
    cam_from_world, K = _ground_truth(1000, 750, n=2)
    batch, transforms = preprocess_vggt([np.zeros((750, 1000, 3), np.uint8)] * 2)
    outputs, _ = _outputs_from_truth(cam_from_world, K, transforms)
    capped = decode_vggt_outputs(outputs, transforms, ["a", "b"], MODEL, max_depth_side=500)
    assert capped.depth[0].shape == (375, 500)
    t = transforms[0]
    ys, xs = (np.mgrid[0:375, 0:500] + 0.5) * 2.0  # original-pixel coordinates of the capped centres
    expected = 2.0 + 0.001 * (xs * t.scale_x + t.offset_x) + 0.002 * (ys * t.scale_y + t.offset_y)
    np.testing.assert_allclose(capped.depth[0][2:-2, 2:-2], expected[2:-2, 2:-2], rtol=1e-5)
    # World points use intrinsics scaled to the grid: same as unprojecting the original coordinates.
    kinv = np.linalg.inv(K[0])
    rays = np.stack([xs, ys, np.ones_like(xs)], -1) @ kinv.T
    cam_pts = rays * expected[..., None]
    world = (cam_pts - cam_from_world[0][:, 3]) @ cam_from_world[0][:, :3]
    np.testing.assert_allclose(capped.world_points(0)[2:-2, 2:-2], world[2:-2, 2:-2], rtol=1e-4, atol=1e-5)


def test_nan_output_is_rejected():
    cam_from_world, K = _ground_truth(320, 240, n=2)
    batch, transforms = preprocess_vggt([np.zeros((240, 320, 3), np.uint8)] * 2)
    outputs, _ = _outputs_from_truth(cam_from_world, K, transforms)
    outputs["depth"][0, 1, 5, 5, 0] = np.nan
    with pytest.raises(ModelError, match="non-finite"):
        decode_vggt_outputs(outputs, transforms, ["a", "b"], MODEL)


def test_outputs_without_batch_axis_are_accepted():
    cam_from_world, K = _ground_truth(320, 240, n=3)
    batch, transforms = preprocess_vggt([np.zeros((240, 320, 3), np.uint8)] * 3)
    outputs, _ = _outputs_from_truth(cam_from_world, K, transforms)
    stripped = {
        "pose_enc": outputs["pose_enc"][0],
        "depth": outputs["depth"][0, ..., 0],
        "depth_conf": outputs["depth_conf"][0],
    }
    pred = decode_vggt_outputs(stripped, transforms, ["a", "b", "c"], MODEL)
    np.testing.assert_allclose(pred.cam_from_world, cam_from_world, rtol=1e-4, atol=1e-5)


def test_reference_sizes():
    """Crop: width 518, height rounded to a multiple of 14 (then cropped to 518); pad: 518 x 518."""
    img = np.zeros((480, 640, 3), np.uint8)
    assert preprocess_vggt([img])[0].shape == (1, 3, 392, 518)
    assert preprocess_vggt([img], PreprocessMode.PAD)[0].shape == (1, 3, 518, 518)
    tall = np.zeros((1000, 500, 3), np.uint8)
    assert preprocess_vggt([tall])[0].shape == (1, 3, 518, 518)
    pad = preprocess_vggt([img], PreprocessMode.PAD)[0]
    assert np.all(pad[0, :, 0, :] == 1.0), "pad mode pads with white"
