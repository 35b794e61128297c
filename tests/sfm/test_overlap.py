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
