"""Global alignment of exact (and noisy) pairwise point maps against ground-truth cameras and depth.

The scene is analytic: a closed box room with a sphere, seen by cameras on an orbit; z-depth is the
exact ray-surface distance at each pixel centre (COLMAP rule), so pairwise point maps built from it
are what a perfect DUSt3R would output (each pair in its own random scale).
"""

import numpy as np
import pytest

from ffrecon.errors import FFReconError
from ffrecon.geometry.metrics import pose_errors
from ffrecon.geometry.poses import look_at_cam_from_world, transform_points
from ffrecon.geometry.projection import pixel_centers, unproject_depth
from ffrecon.geometry.rotations import axis_angle_to_matrix
from ffrecon.models.alignment_init import estimate_focal, maximum_spanning_tree
from ffrecon.models.global_alignment import AlignmentOptions, PairPrediction, global_align

SIZE_HW = (32, 48)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def room_depth(cam_from_world, K, size_hw):
    """``[H, W]`` exact z-depth of the box room [-3, 3]^3 with a sphere (radius 0.7) at the origin."""
    h, w = size_hw
    center = -cam_from_world[:, :3].T @ cam_from_world[:, 3]
    uv = pixel_centers(h, w)
    dirs_cam = np.concatenate([(uv - K[:2, 2]) / [K[0, 0], K[1, 1]], np.ones((h, w, 1))], axis=-1)
    dirs = dirs_cam @ cam_from_world[:, :3]  # world directions with unit z in the camera
    t = np.full((h, w), np.inf)
    for axis in range(3):
        for sign in (1.0, -1.0):
            along = sign * dirs[..., axis]
            hit = (3.0 - sign * center[axis]) / np.where(along > 1e-9, along, 1.0)
            t = np.where(along > 1e-9, np.minimum(t, hit), t)
    a, b, c = (dirs**2).sum(-1), (dirs * center).sum(-1), center @ center - 0.7**2
    disc = b**2 - a * c
    t_sphere = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
    return np.where((disc > 0) & (t_sphere > 0), np.minimum(t, t_sphere), t)


def orbit_scene(num_views, size_hw, seed):
    """``(cam_from_world [N, 3, 4], K [N, 3, 3], depth [N, H, W])``; focals differ per view."""
    rng = np.random.default_rng(seed)
    h, w = size_hw
    poses, Ks = [], []
    for k in range(num_views):
        angle = 1.2 * np.pi * k / num_views + rng.normal(0, 0.05)
        center = np.array([1.8 * np.cos(angle), 1.8 * np.sin(angle), rng.uniform(-0.5, 0.5)])
        poses.append(look_at_cam_from_world(center, rng.normal(0, 0.2, 3)))
        f = rng.uniform(0.8, 1.1) * w
        Ks.append(np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]]))
    depth = np.stack([room_depth(p, K, size_hw) for p, K in zip(poses, Ks)])
    return np.stack(poses), np.stack(Ks), depth


def exact_pairs(pairs, cam_from_world, K, depth, seed):
    """What a perfect pairwise model outputs: both views in view i's frame, in a random pair scale."""
    rng = np.random.default_rng(seed)
    world = [unproject_depth(depth[v], K[v], cam_from_world[v]) for v in range(len(K))]
    out = []
    for i, j in pairs:
        scale = rng.uniform(0.5, 2.0)
        pts_i = unproject_depth(depth[i], K[i]) * scale
        pts_j = transform_points(cam_from_world[i], world[j]) * scale
        conf_i, conf_j = 1 + 5 * rng.random((2, *depth[i].shape))
        out.append(
            PairPrediction(
                i,
                j,
                pts_i.astype(np.float32),
                conf_i.astype(np.float32),
                pts_j.astype(np.float32),
                conf_j.astype(np.float32),
            )
        )
    return out


COMPLETE = [(i, j) for i in range(6) for j in range(6) if i != j]
SLIDING = [(i, j) for i in range(6) for j in range(6) if i != j and abs(i - j) <= 2]
ONE_REF_ONE_WAY = [(0, j) for j in range(1, 6)]  # views 1..5 are never first: the PnP path


@pytest.mark.parametrize(
    "pairs", [COMPLETE, SLIDING, ONE_REF_ONE_WAY], ids=["complete", "sliding_window", "one_reference_one_way"]
)
def test_exact_pairs_recover_ground_truth(pairs):
    """The last Adam iterate (not the best one, which may be the exact initialisation) is checked."""
    cam_from_world, K, depth = orbit_scene(6, SIZE_HW, seed=0)
    result = global_align(
        exact_pairs(pairs, cam_from_world, K, depth, seed=1), SIZE_HW, AlignmentOptions(keep_best=False)
    )
    assert result.best_iteration == result.iterations == 300
    errors = pose_errors(result.cam_from_world, cam_from_world)
    assert errors.auc[5] >= 0.99  # acceptance criterion
    assert errors.median_rotation_deg < 0.05
    np.testing.assert_allclose(result.focal, K[:, 0, 0], rtol=0.01)
    # Depth in the estimate's scale; the Sim(3) of the pose metric brings it to ground truth units.
    rel = np.abs(result.depth * errors.est_to_ref.scale / depth - 1)
    assert np.median(rel) < 1e-3 and rel.max() < 0.01
    # Gauge: the world is view 0's camera.
    np.testing.assert_allclose(result.cam_from_world[0], np.eye(3, 4), atol=1e-9)
    np.testing.assert_allclose(
        result.cam_from_world[:, :, :3] @ result.cam_from_world[:, :, :3].transpose(0, 2, 1),
        np.broadcast_to(np.eye(3), (6, 3, 3)),
        atol=1e-9,
    )
    assert result.conf.shape == (6, *SIZE_HW) and result.conf.min() >= 1


def test_optimisation_improves_on_noisy_pairs():
    """Each pair's view j is rotated by ~2 degrees and points get 1% depth noise: the spanning tree
    accumulates the errors of its edges, the 3D alignment over all pairs averages them out."""
    cam_from_world, K, depth = orbit_scene(6, SIZE_HW, seed=0)
    rng = np.random.default_rng(5)
    noisy = []
    for p in exact_pairs(COMPLETE, cam_from_world, K, depth, seed=1):
        rot = axis_angle_to_matrix(rng.normal(size=3) * np.radians(2.0) / np.sqrt(3)).astype(np.float32)
        noise_i, noise_j = (1 + 0.01 * rng.normal(size=(2, *SIZE_HW, 1))).astype(np.float32)
        noisy.append(
            PairPrediction(p.i, p.j, p.pts_i_in_i * noise_i, p.conf_i, (p.pts_j_in_i @ rot.T) * noise_j, p.conf_j)
        )
    result = global_align(noisy, SIZE_HW)
    initial = pose_errors(result.initial_cam_from_world, cam_from_world)
    final = pose_errors(result.cam_from_world, cam_from_world)
    assert result.loss < 0.8 * result.initial_loss and result.best_iteration > 100
    assert final.median_rotation_deg < 0.5 * initial.median_rotation_deg
    assert final.auc[5] > initial.auc[5] + 0.1
    np.testing.assert_allclose(result.focal, K[:, 0, 0], rtol=0.01)


def test_coarse_depth_unknowns():
    cam_from_world, K, depth = orbit_scene(4, SIZE_HW, seed=3)
    pairs = [(i, j) for i in range(4) for j in range(4) if i != j]
    result = global_align(
        exact_pairs(pairs, cam_from_world, K, depth, seed=1),
        SIZE_HW,
        AlignmentOptions(depth_downsample=2, iterations=150),
    )
    errors = pose_errors(result.cam_from_world, cam_from_world)
    assert errors.auc[5] >= 0.99
    np.testing.assert_allclose(result.focal, K[:, 0, 0], rtol=0.01)
    assert result.depth.shape == (4, *SIZE_HW) and result.iterations == 150


def test_initialisation_alone_is_exact_on_exact_pairs():
    cam_from_world, K, depth = orbit_scene(5, SIZE_HW, seed=2)
    pairs = [(0, 1), (1, 0), (1, 2), (2, 1), (2, 3), (3, 2), (3, 4), (4, 3), (4, 0), (0, 4)]
    result = global_align(exact_pairs(pairs, cam_from_world, K, depth, seed=4), SIZE_HW, AlignmentOptions(iterations=0))
    errors = pose_errors(result.cam_from_world, cam_from_world)
    assert errors.median_rotation_deg < 1e-3 and errors.ate_relative < 1e-5
    np.testing.assert_allclose(result.focal, K[:, 0, 0], rtol=1e-5)
    assert result.loss == pytest.approx(result.initial_loss) and result.loss < 1e-5


def test_estimate_focal_exact_and_robust_to_outliers():
    rng = np.random.default_rng(0)
    h, w, f = 30, 40, 37.0
    depth = rng.uniform(1, 3, (h, w))
    pts = unproject_depth(depth, np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]]))
    assert estimate_focal(pts, np.ones((h, w)), (h, w)) == pytest.approx(f, rel=1e-6)
    pts[:3] *= np.array([2.0, -1.0, 1.0])  # 10% of the pixels wrong
    assert estimate_focal(pts, np.ones((h, w)), (h, w)) == pytest.approx(f, rel=0.01)


def _pair(i, j, conf):
    shape = (4, 6)
    ones = np.ones(shape, np.float32)
    return PairPrediction(
        i, j, np.ones((*shape, 3), np.float32), ones * conf, np.ones((*shape, 3), np.float32), ones * conf
    )


def test_maximum_spanning_tree_keeps_the_most_confident_edges():
    pairs = [_pair(0, 1, 5.0), _pair(1, 2, 4.0), _pair(0, 2, 2.0), _pair(2, 0, 3.0), _pair(2, 3, 1.5)]
    assert sorted(maximum_spanning_tree(4, pairs)) == [0, 1, 4]
    with pytest.raises(FFReconError, match="do not connect"):
        maximum_spanning_tree(4, pairs[:4])


def test_bad_inputs_raise_readable_errors():
    with pytest.raises(FFReconError, match="expected points"):
        global_align([_pair(0, 1, 2.0)], (5, 6))
    with pytest.raises(FFReconError, match="in no pair"):
        global_align([_pair(0, 2, 2.0)], (4, 6))
    with pytest.raises(FFReconError, match="at least one pair"):
        global_align([], (4, 6))
