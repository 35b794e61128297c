"""The exports fuse the depth maps with the refined cameras by moving the model's own fusion (each frame reduced
alone, FeedForwardResult.frame_clouds) instead of a second pass over the depth maps and photos (issue 40)."""

from __future__ import annotations

import numpy as np
import pytest

from ffrecon.export.stage import fuse_with_final_cameras, with_final_cameras
from ffrecon.final_cameras import CameraSource, FinalCameras
from ffrecon.formats.pointcloud import FuseOptions, fuse_prediction, fuse_prediction_frames
from ffrecon.geometry.rotations import axis_angle_to_matrix
from ffrecon.types import ModelFamily, ModelInfo, PinholeCamera, Prediction


def _scene(n=5, h=30, w=40):
    """A prediction whose depth maps are half the photos' size (depth_camera scales), and final cameras for
    frames 0, 2, 3, 4 (frame 1 left out) turned, moved and with other intrinsics."""
    rng = np.random.default_rng(3)
    camera = PinholeCamera(2 * w, 2 * h, 70.0, 72.0, w, h)
    poses = np.tile(np.eye(3, 4), (n, 1, 1))
    poses[:, 0, 3] = -0.1 * np.arange(n)
    depth = tuple((2 + rng.uniform(0, 0.5, (h, w))).astype(np.float32) for _ in range(n))
    conf = tuple((1 + rng.uniform(0, 5, (h, w))).astype(np.float32) for _ in range(n))
    names = tuple(f"f{k}.png" for k in range(n))
    prediction = Prediction(names, poses, (camera,) * n, depth, conf, ModelInfo("m", ModelFamily.MULTIVIEW))
    images = [rng.integers(0, 256, (2 * h, 2 * w, 3), dtype=np.uint8) for _ in range(n)]
    kept = (0, 2, 3, 4)
    refined = poses[list(kept)].copy()
    for p in refined:
        p[:, :3] = axis_angle_to_matrix(rng.normal(0, 0.03, 3)) @ p[:, :3]
        p[:, 3] += rng.normal(0, 0.02, 3)
    cameras = tuple(PinholeCamera(2 * w, 2 * h, 74.0 + k, 70.0, w + 1.5, h - 0.5) for k in kept)
    final = FinalCameras(kept, tuple(names[k] for k in kept), refined, cameras, CameraSource.REFINED)
    return prediction, images, final


def _never(indices):
    raise AssertionError("the photos were read again")


def _sorted(xyz):
    return xyz[np.lexsort(xyz.T[::-1])]


def test_moved_frames_are_the_points_a_second_fusion_makes():
    """With a voxel far below the pixels' spacing (each point its own voxel) the moved frames are exactly the
    second fusion's points: intrinsics, poses and the frames left out all carried over."""
    prediction, images, final = _scene()
    options = FuseOptions(voxel_fraction=1e-9, remove_outliers=False)
    _, _, clouds = fuse_prediction_frames(prediction, images, options)
    moved, rgb = fuse_with_final_cameras(prediction, final, _never, options, clouds)
    again, rgb_again = fuse_prediction(
        with_final_cameras(prediction, final), [images[k] for k in final.indices], options
    )
    assert len(moved) == len(again) > 1000
    np.testing.assert_allclose(_sorted(moved), _sorted(again), rtol=0, atol=1e-5)  # float32 depth
    np.testing.assert_allclose(np.sort(rgb, axis=0), np.sort(rgb_again, axis=0), atol=1e-6)


def test_moved_frames_at_the_default_voxel_are_near_the_second_fusion():
    prediction, images, final = _scene()
    _, _, clouds = fuse_prediction_frames(prediction, images)
    moved, _ = fuse_with_final_cameras(prediction, final, _never, FuseOptions(), clouds)
    again, _ = fuse_prediction(with_final_cameras(prediction, final), [images[k] for k in final.indices])
    assert abs(len(moved) - len(again)) < 0.1 * len(again)
    nearest = np.sqrt(((moved[:, None] - again[None]) ** 2).sum(-1)).min(1)
    assert np.median(nearest) < clouds.voxel


def test_without_the_frames_a_resumed_run_writes_the_same_cloud():
    """A resumed run has no frame clouds (they are not in the stage's record): the model's fusion is made again
    from the photos, then moved: the same cloud as the run that kept them."""
    prediction, images, final = _scene()
    _, _, clouds = fuse_prediction_frames(prediction, images)
    kept = fuse_with_final_cameras(prediction, final, _never, FuseOptions(), clouds)
    with pytest.raises(AssertionError, match="read again"):
        fuse_with_final_cameras(prediction, final, _never, FuseOptions(), None)
    again = fuse_with_final_cameras(prediction, final, lambda idx: [images[k] for k in idx], FuseOptions(), None)
    np.testing.assert_array_equal(again[0], kept[0])
    np.testing.assert_array_equal(again[1], kept[1])
