"""The capture's overlap check matches each pair of nearby frames once, with the verdicts of
matching every frame with each of its neighbours both ways (issue 40)."""

from __future__ import annotations

import cv2
import numpy as np

from ffrecon.capture import quality
from ffrecon.capture.quality import QualityOptions, assess_capture, measure_frame


def _texture(seed: int, h: int = 300, w: int = 560) -> np.ndarray:
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (h // 4, w // 4, 3), dtype=np.uint8)
    return cv2.GaussianBlur(cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC), (0, 0), 1.0)


def _frames():
    """Six 320x240 views sliding over one texture, the fourth of another texture (no overlap with any)."""
    scene, other = _texture(0), _texture(1)
    frames = [scene[20:260, 30 * k : 30 * k + 320].copy() for k in range(6)]
    frames[3] = other[30:270, 100:420].copy()
    return [f"f{k}.png" for k in range(6)], [measure_frame(f) for f in frames]


def _both_ways(measures, neighbours):
    """The check as it was: each frame matched with each neighbour, so every pair twice."""
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    best = [-1] * len(measures)
    for i in range(len(measures)):
        for j in range(max(0, i - neighbours), min(len(measures), i + neighbours + 1)):
            if j != i:
                best[i] = max(best[i], quality._orb_inliers(measures[i], measures[j], matcher))
    return best


def test_the_overlap_verdicts_are_those_of_matching_both_ways():
    names, measures = _frames()
    options = QualityOptions()
    checked = assess_capture(names, measures, options)
    assert checked.flagged("overlap") == ["f3.png"]
    reference = _both_ways(measures, options.overlap_neighbours)
    assert [b < options.min_overlap_matches for b in checked.best_neighbour_matches] == [
        b < options.min_overlap_matches for b in reference
    ]
    assert min(b for k, b in enumerate(checked.best_neighbour_matches) if k != 3) > 3 * options.min_overlap_matches


def test_each_nearby_pair_is_matched_once(monkeypatch):
    _, measures = _frames()
    seen = []
    real = quality._orb_inliers
    monkeypatch.setattr(quality, "_orb_inliers", lambda a, b, m: seen.append((id(a), id(b))) or real(a, b, m))
    quality._best_neighbour_matches(measures, 2)
    assert len(seen) == 5 + 4  # pairs one and two frames apart, once each (both ways: 18)
    assert len({frozenset(p) for p in seen}) == len(seen)
    assert quality._best_neighbour_matches(measures[:1], 2) == [-1]  # a single frame: nothing to match


def test_farther_pairs_are_matched_only_for_frames_short_of_the_bar(monkeypatch):
    """With the bar given, a pair two frames apart is matched only where one of its frames shares fewer inliers
    than the bar with its nearest neighbours (issue 40: half the ORB matching on ordered captures); the verdicts
    are those of matching every pair."""
    names, measures = _frames()
    options = QualityOptions()
    seen = []
    real = quality._orb_inliers
    monkeypatch.setattr(quality, "_orb_inliers", lambda a, b, m: seen.append((id(a), id(b))) or real(a, b, m))
    best = quality._best_neighbour_matches(measures, 2, options.min_overlap_matches)
    index = {id(m): k for k, m in enumerate(measures)}
    far = sorted((index[a], index[b]) for a, b in seen if abs(index[a] - index[b]) == 2)
    assert len(seen) - len(far) == 5 and far == [(1, 3), (3, 5)]  # only those of f3, which matches nothing
    full = quality._best_neighbour_matches(measures, 2)
    bar = options.min_overlap_matches
    assert [b < bar for b in best] == [b < bar for b in full] and min(best) >= 0
