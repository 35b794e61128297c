"""The photometric check's rule for a frame whose weak pairs dispute its camera (issue 39): the pairs and the photos
must agree on how far it turned. Numbers from the sweeps' logs (tools/sweep_families.py, tuning seeds 213-223 and
room seed 236)."""

from ffrecon.sfm.verify.photometric import PhotometricCheck, PhotometricOptions, PhotometricScore

NAN = float("nan")


def _check(score: PhotometricScore) -> PhotometricCheck:
    return PhotometricCheck(0.96, {"frame.png": score}, PhotometricOptions())


def test_pairs_and_photos_that_agree_on_the_turn_contradict_it():
    """Room 236 (plain walls), frame 6 26 deg off: one 37-match pair 26.5 deg from its camera; nothing covers it
    near its camera; its photo fits 0.83 turned 33 deg."""
    check = _check(PhotometricScore(NAN, NAN, 0.83, 33.2))
    assert check.turned_like("frame.png", 26.5)
    assert "turned 33 deg" in check.describe_turned("frame.png", 26.5)


def test_a_far_fit_that_disagrees_with_the_pairs_or_is_weak_says_nothing():
    # room 223, frame 5 (2 deg off, a good frame): fits 0.91 turned 32 deg, its pairs 3.4 deg from its camera
    assert not _check(PhotometricScore(NAN, NAN, 0.91, 31.6)).turned_like("frame.png", 3.4)
    assert not _check(PhotometricScore(NAN, NAN, 0.83, 33.2)).turned_like("frame.png", 12.0)  # 21 deg apart
    assert not _check(PhotometricScore(NAN, NAN, 0.31, 33.5)).turned_like("frame.png", 30.0)  # under min_best
    assert not _check(PhotometricScore(0.9, 0.92, 0.85, 30.0)).turned_like("frame.png", 30.0)  # fits better near
    assert not _check(PhotometricScore(NAN, NAN, 0.85, 15.0)).turned_like("frame.png", 14.0)  # under min_turn_deg
    assert not _check(PhotometricScore(NAN, NAN, NAN, 0.0)).turned_like("frame.png", 26.0)  # nothing covers it
