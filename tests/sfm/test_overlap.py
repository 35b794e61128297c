"""Overlap of frames from the feed-forward geometry, on exact ground truth."""

from __future__ import annotations

import numpy as np

from ffrecon.geometry import overlap
from ffrecon.geometry.overlap import OverlapOptions, overlap_graph, select_pairs
from ffrecon.geometry.projection import pixel_centers
from ffrecon.types import ModelFamily, ModelInfo, PinholeCamera, Prediction


def test_overlap_follows_the_orbit(orbit24):
    graph = overlap_graph(orbit24.prediction)
    score = graph.score()
    n = 24
    neighbours = np.array([score[i, (i + 1) % n] for i in range(n)])
    opposite = np.array([score[i, (i + 12) % n] for i in range(n)])
    assert neighbours.min() > 0.3  # 15 degrees apart, looking at the same objects (noisy poses)
    assert opposite.max() < neighbours.min()
    # Every frame is matched with its two orbit neighbours, and far fewer pairs than exhaustive.
    pairs = {tuple(p) for p in graph.pairs.tolist()}
    for i in range(n):
        assert tuple(sorted((i, (i + 1) % n))) in pairs
    assert len(pairs) < n * (n - 1) // 2 // 2


def test_select_pairs_caps_and_falls_back_to_neighbours():
    n = 6
    overlap = np.full((n, n), 0.9)
    overlap[5, :] = overlap[:, 5] = 0.0  # frame 5 overlaps nothing according to the prediction
    np.fill_diagonal(overlap, 1.0)
    pairs = select_pairs(overlap, OverlapOptions(max_pairs_per_image=2, min_pairs_per_image=0, fallback_neighbours=1))
    counts = np.bincount(pairs.ravel(), minlength=n)
    assert counts[:5].max() <= 4  # capped (a frame can also be chosen by others)
    assert [4, 5] in pairs.tolist() and counts[5] == 1  # its index neighbour, the only fallback


def test_select_pairs_keeps_loop_candidates():
    """A looped path of 60 frames: each frame overlaps its near neighbours well, and the frames at the end
    revisit the start less well; with a tight cap the near neighbours fill it, the revisits still come."""
    n = 60
    index = np.arange(n)
    gap = np.abs(index[:, None] - index[None, :])
    overlap = np.where(gap <= 6, 0.9 - 0.05 * gap, 0.0)
    for a in range(5):
        for b in range(55, 60):
            overlap[a, b] = overlap[b, a] = 0.4  # the revisit
    tight = dict(max_pairs_per_image=4, min_pairs_per_image=2)
    with_loops = {tuple(p) for p in select_pairs(overlap, OverlapOptions(**tight)).tolist()}
    without = {tuple(p) for p in select_pairs(overlap, OverlapOptions(**tight, loop_pairs_per_image=0)).tolist()}
    revisits = {(a, b) for a in range(5) for b in range(55, 60)}
    assert not without & revisits, "the cap alone drops every revisit"
    assert len(with_loops & revisits) >= 5 and with_loops >= without
    assert all(abs(a - b) <= 6 or (a, b) in revisits for a, b in with_loops)


def _corridor(n: int) -> Prediction:
    """Cameras walking along a wall (0.4 apart, the wall 3 away, 60 degrees of view), every fifth turned
    about its vertical axis and the last looking away from the wall: far frames share nothing."""
    h, w = 48, 64
    camera = PinholeCamera(w, h, 55.0, 55.0, 32.0, 24.0)
    poses = []
    for k in range(n):
        yaw = np.radians(20.0 if k % 5 == 0 else 0.0) + (np.pi if k == n - 1 else 0.0)
        rot = np.array([[np.cos(yaw), 0, -np.sin(yaw)], [0, 1, 0], [np.sin(yaw), 0, np.cos(yaw)]])
        centre = np.array([0.4 * k, 0.0, 0.0])
        poses.append(np.hstack([rot, (-rot @ centre)[:, None]]))
    poses = np.array(poses)
    depth = []
    for k in range(n):  # z-depth of the wall z = 3 (+ a ripple) along each pixel's ray
        uv = pixel_centers(h, w).reshape(-1, 2)
        rays = np.column_stack([(uv - [camera.cx, camera.cy]) / camera.fx, np.ones(h * w)]) @ poses[k][:, :3]
        centre = -poses[k][:, :3].T @ poses[k][:, 3]
        t = (3.0 - centre[2]) / np.where(np.abs(rays[:, 2]) > 1e-9, rays[:, 2], 1e-9)
        hit = centre + t[:, None] * rays
        t *= 1 + 0.01 * np.sin(hit[:, 0] * 5)
        depth.append(np.where(t > 0, t, 0.0).reshape(h, w).astype(np.float32))
    conf = tuple((d > 0).astype(np.float32) * 2 for d in depth)
    info = ModelInfo("corridor", ModelFamily.MULTIVIEW, simulated=True)
    return Prediction(tuple(f"{k}.png" for k in range(n)), poses, (camera,) * n, tuple(depth), conf, info)


def test_frustum_test_skips_projections_and_changes_no_overlap(monkeypatch):
    """Projecting only the points that may be in view gives the overlap of projecting every frame's points into
    every frame, exactly; on a 40-frame corridor most of the points are never projected into a frame."""
    prediction = _corridor(40)
    rng = np.random.default_rng(0)
    groups = overlap._Groups.of([overlap._sample_points(prediction, i, OverlapOptions(), rng) for i in range(40)])
    tested = np.array([overlap._in_view(groups, prediction, j) for j in range(40)])  # [frame j, group]
    fast = overlap.overlap_matrix(prediction)
    monkeypatch.setattr(overlap, "_in_view", lambda groups, pred, j: np.ones(len(groups.count), bool))
    every = overlap.overlap_matrix(prediction)
    np.testing.assert_array_equal(fast, every)
    projected = (tested * groups.count).sum() / (40 * groups.count.sum())
    assert projected < 0.3, projected
    assert fast[0, 1] > 0.5 and fast[0, 20] == 0 and fast[39, :39].max() == 0 and fast[:39, 39].max() == 0


def test_long_captures_measure_only_the_pairs_a_coarse_pass_finds():
    """From ``coarse_from_frames`` frames the overlap is first estimated on a tenth of the samples: on the
    corridor every pair that overlaps by 10 % or more is measured exactly as before, the others stay under
    the coarse threshold, and the same pairs are chosen."""
    prediction = _corridor(40)
    exact = overlap.overlap_matrix(prediction, OverlapOptions())
    coarse_first = overlap.overlap_matrix(prediction, OverlapOptions(coarse_from_frames=10))
    both = np.minimum(exact, exact.T)
    np.testing.assert_array_equal(coarse_first[both >= 0.1], exact[both >= 0.1])
    assert (coarse_first != exact).any(), "some pairs kept the coarse estimate"
    assert (np.maximum(coarse_first, coarse_first.T)[coarse_first != exact] < 0.05).all()
    np.testing.assert_array_equal(select_pairs(coarse_first), select_pairs(exact))


def test_long_captures_measure_only_the_pairs_that_can_be_chosen():
    """Where many frames overlap (an orbit of a room: 210 partners a frame at 500 frames), only each frame's
    best partners by the coarse estimate, ``coarse_margin`` times as many as can be chosen, are measured on
    every sample; the chosen pairs are those of the exact overlap."""
    prediction = _corridor(40)
    small = dict(max_pairs_per_image=2, min_pairs_per_image=1, loop_pairs_per_image=1, loop_min_gap=30)
    exact = overlap.overlap_matrix(prediction, OverlapOptions(**small))
    ranked = overlap.overlap_matrix(prediction, OverlapOptions(coarse_from_frames=10, coarse_margin=2, **small))
    both = np.minimum(exact, exact.T)
    unmeasured = (ranked != exact) & (both >= 0.1)
    assert unmeasured.any(), "some overlapping pairs kept the coarse estimate"
    # Each frame's 6 best and its 2 best revisits (30 frames apart or more) were measured exactly.
    for i in range(40):
        best = np.argsort(-both[i] + 2 * np.eye(40)[i], kind="stable")[:3]
        np.testing.assert_array_equal(ranked[i, best], exact[i, best])
    np.testing.assert_array_equal(
        select_pairs(ranked, OverlapOptions(**small)), select_pairs(exact, OverlapOptions(**small))
    )
