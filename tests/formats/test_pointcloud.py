"""Fusing depth maps: reducing each frame first keeps exactly the voxels of the whole cloud at once."""

import numpy as np

from ffrecon.formats.pointcloud import FuseOptions, downsample


def _voxels(xyz: np.ndarray, size: float) -> set[tuple[int, int, int]]:
    return set(map(tuple, np.floor(xyz / size).astype(int)))


def test_frame_by_frame_reduction_keeps_the_voxels_of_the_union():
    rng = np.random.default_rng(0)
    # 6 overlapping "frames" of a noisy plane with a bump: many points per voxel, shared voxels.
    frames, colours = [], []
    for k in range(6):
        uv = rng.uniform(-1, 1, (50_000, 2)) + [0.2 * k, 0.0]
        z = 0.3 * np.exp(-4 * (uv**2).sum(1)) + rng.normal(0, 0.002, len(uv))
        frames.append(np.column_stack([uv, z]))
        colours.append(rng.uniform(0, 1, (len(uv), 3)).astype(np.float32))
    union = np.concatenate(frames)
    options = FuseOptions(remove_outliers=False)
    lo, hi = np.quantile(union, [0.02, 0.98], axis=0)
    size = float(np.linalg.norm(hi - lo)) * options.voxel_fraction

    by_frame, rgb = downsample(frames, colours, options)
    at_once, _ = downsample([union], [np.concatenate(colours)], options)

    assert len(by_frame) == len(at_once) == len(_voxels(union, size))
    assert _voxels(by_frame, size) == _voxels(union, size)  # one point per occupied voxel, inside it
    assert rgb.dtype == np.float32 and rgb.shape == (len(by_frame), 3) and 0 <= rgb.min() <= rgb.max() <= 1
    assert len(by_frame) < len(union) / 3  # and it did reduce


def test_the_fused_cloud_is_the_same_in_every_call():
    """open3d's voxel reduction returns its voxels in a varying order; a resumed run must write the same file."""
    rng = np.random.default_rng(1)
    frames = [rng.uniform(0, 1, (30_000, 3)) for _ in range(3)]
    colours = [rng.uniform(0, 1, (30_000, 3)).astype(np.float32) for _ in range(3)]
    first = downsample(frames, colours)
    for _ in range(3):
        again = downsample(frames, colours)
        np.testing.assert_allclose(again[0], first[0], rtol=0, atol=1e-12)
        np.testing.assert_allclose(again[1], first[1], rtol=0, atol=1e-6)


def test_fusing_frame_by_frame_gives_the_cloud_of_all_frames_at_once():
    """fuse_prediction makes and reduces one frame's points at a time (bounded memory); the cloud is exactly
    downsample() of every frame's points collected first."""
    from ffrecon.formats.pointcloud import _frame_points, _picked, fuse_prediction
    from ffrecon.types import ModelFamily, ModelInfo, PinholeCamera, Prediction

    rng = np.random.default_rng(1)
    n, h, w = 5, 60, 80
    camera = PinholeCamera(w, h, 70.0, 70.0, w / 2, h / 2)
    poses = np.tile(np.eye(3, 4), (n, 1, 1))
    poses[:, 0, 3] = -0.1 * np.arange(n)  # a sideways walk
    depth = tuple((2 + rng.uniform(0, 0.5, (h, w))).astype(np.float32) for _ in range(n))
    conf = tuple((1 + rng.uniform(0, 5, (h, w))).astype(np.float32) for _ in range(n))
    prediction = Prediction(
        tuple(f"f{k}.png" for k in range(n)), poses, (camera,) * n, depth, conf, ModelInfo("m", ModelFamily.MULTIVIEW)
    )
    images = [rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for _ in range(n)]
    options = FuseOptions(max_points_per_frame=1000)
    streamed = fuse_prediction(prediction, images, options)
    frames = [_frame_points(prediction, images, k, _picked(prediction, k, options)) for k in range(n)]
    at_once = downsample([f[0] for f in frames], [f[1] for f in frames], options)
    assert len(streamed[0]) > 100
    np.testing.assert_array_equal(streamed[0], at_once[0])
    np.testing.assert_array_equal(streamed[1], at_once[1])
