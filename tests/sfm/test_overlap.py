"""Overlap of frames from the feed-forward geometry, on exact ground truth."""

from __future__ import annotations

import numpy as np

from ffrecon.sfm.overlap import OverlapOptions, overlap_graph, select_pairs


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
