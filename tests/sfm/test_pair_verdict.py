"""A frame the refinement did not hold, judged on its verified pairs: weighed, never removed by one weak pair."""

from ffrecon.sfm.verify.frames import _pair_verdict
from ffrecon.sfm.verify.verdicts import EvidenceOptions, FrameVerdict

OPTIONS = EvidenceOptions()


def _pair(inliers: int, gap_deg: float) -> tuple:
    """(partner, inliers, gap between the pair's relative rotation and the model's, degrees)."""
    return ("partner", inliers, gap_deg)


def test_one_weak_pair_does_not_remove_a_frame():
    """The street family's case (tuning seed 101): 21 matches, 13.7 deg from a model pose 3.1 deg off."""
    e = _pair_verdict("f", "weak", [_pair(21, 13.7)], OPTIONS)
    assert e.verdict is FrameVerdict.UNCHECKED and e.status.kept and "too weak" in e.why


def test_a_decisive_pair_contradicts():
    e = _pair_verdict("f", "weak", [_pair(150, 24.0)], OPTIONS)
    assert e.verdict is FrameVerdict.CONTRADICTED and not e.status.kept


def test_two_weak_pairs_that_both_disagree_contradict():
    """Two independent pairs each put the frame far from the model, whether or not they agree on where."""
    e = _pair_verdict("f", "weak", [_pair(30, 25.0), _pair(25, 40.0)], OPTIONS)
    assert e.verdict is FrameVerdict.CONTRADICTED


def test_disagreeing_pairs_outweighed_by_agreeing_ones_do_not_contradict():
    e = _pair_verdict("f", "weak", [_pair(120, 15.0), _pair(100, 2.0), _pair(90, 1.0)], OPTIONS)
    assert e.verdict is FrameVerdict.UNCHECKED
