"""An unchecked frame whose dense tracks from the model's prediction found almost nothing, where the other frames
tracked found theirs, is left out (:func:`ffrecon.sfm.verify.signs._dense_misfits`, issue 39); a frame the dense
tracking barely tried, or a capture where no frame's tracks held, is not judged by it."""

from types import SimpleNamespace

from ffrecon.sfm.refine.dense import DenseStats
from ffrecon.sfm.verify.signs import _dense_misfits
from ffrecon.sfm.verify.verdicts import CameraEvidence, CameraStatus, EvidenceOptions

NAMES = [f"frame_{k:03d}.png" for k in range(5)]


def _refine(pairs: list[tuple[int, int, int, int]]):
    """A refinement whose dense evidence tracked ``pairs``: (frame, frame, corners predicted, verified)."""
    named = tuple((NAMES[a], NAMES[b], tried, kept) for a, b, tried, kept in pairs)
    per_frame = {n: sum(p[3] for p in named if n in p[:2]) for n in NAMES}
    stats = DenseStats(tuple(NAMES), len(pairs), 0, sum(per_frame.values()) // 2, per_frame, 1.0, named)
    return SimpleNamespace(dense=stats)


# frame 0's pairs find nothing; the others verify 30-45 % of what the prediction put inside their partners
WORKING = [(1, 2, 800, 300), (2, 3, 900, 400), (3, 4, 700, 300), (1, 4, 800, 250)]
FRAME_0_OFF = [(0, 1, 900, 0), (0, 2, 1000, 0), *WORKING]


def _unchecked() -> tuple[CameraEvidence, ...]:
    return tuple(
        CameraEvidence(
            n, CameraStatus.UNCHECKED, f"{n}: 0 verified matches; no other evidence: the model's camera is kept"
        )
        for n in NAMES
    )


def test_a_frame_whose_predicted_corners_were_not_found_is_left_out():
    out = _dense_misfits(_unchecked(), _refine(FRAME_0_OFF), EvidenceOptions())
    assert out[0].status is CameraStatus.CONTRADICTED and not out[0].status.kept
    assert "verified 0 of the 1900 corners" in out[0].why and out[0].why.endswith("left out")
    assert all(e.status is CameraStatus.UNCHECKED for e in out[1:])


def test_the_partner_of_a_frame_far_off_is_judged_without_that_pair():
    # frame 1 failed with frame 0 (25 deg off) and on one weak pair; without frame 0 it has too little to judge
    pairs = [(0, 1, 900, 0), (0, 2, 1000, 0), (1, 4, 150, 0), (2, 3, 900, 400), (3, 4, 700, 300), (2, 4, 800, 250)]
    out = _dense_misfits(_unchecked(), _refine(pairs), EvidenceOptions())
    assert out[0].status is CameraStatus.CONTRADICTED
    assert all(e.status is CameraStatus.UNCHECKED for e in out[1:])


def test_a_share_within_the_ratio_of_the_others_is_no_misfit():
    # 8 % where the others verify 30-45 %: weaker, not a camera far off
    out = _dense_misfits(_unchecked(), _refine([(0, 1, 900, 70), (0, 2, 1000, 80), *WORKING]), EvidenceOptions())
    assert all(e.status is CameraStatus.UNCHECKED for e in out)


def test_too_few_predicted_corners_or_no_working_reference_judge_nothing():
    options = EvidenceOptions()
    few = _dense_misfits(_unchecked(), _refine([(0, 1, 90, 0), (0, 2, 100, 0), *WORKING]), options)
    assert few[0].status is CameraStatus.UNCHECKED  # 190 < min_dense_predicted: the prediction barely overlapped
    failing = [(a, b, tried, 0) for a, b, tried, _ in FRAME_0_OFF]
    assert all(e.status is CameraStatus.UNCHECKED for e in _dense_misfits(_unchecked(), _refine(failing), options))


def test_only_unchecked_frames_are_judged():
    evidence = list(_unchecked())
    evidence[0] = CameraEvidence(NAMES[0], CameraStatus.GUIDED, "refined on guided matches", 1.0)
    out = _dense_misfits(tuple(evidence), _refine(FRAME_0_OFF), EvidenceOptions())
    assert out[0].status is CameraStatus.GUIDED


def test_a_frame_whose_dense_tracks_found_few_corners_is_doubted():
    """The weak dense sign counted beside a photometric one (signs._dense_doubted): held-out room 337 (frames
    renumbered 0-4), frame 3 (25 deg off) verified 84 of 1,810 corners (5 %), the others' median 11 %. A frame whose
    only pair is with it is doubted too (the photometric sign must then single out which)."""
    import dataclasses

    from ffrecon.sfm.verify.signs import _dense_doubted

    refine = _refine([(0, 1, 619, 356), (1, 2, 1345, 1116), (2, 3, 1260, 84), (3, 4, 550, 0), (0, 4, 206, 23)])
    assert _dense_doubted(refine, EvidenceOptions()) == frozenset({NAMES[3], NAMES[4]})
    fewer = dataclasses.replace(EvidenceOptions(), min_dense_doubt_predicted=2000)  # none tried that many
    assert _dense_doubted(refine, fewer) == frozenset()
    assert _dense_doubted(_refine(WORKING), EvidenceOptions()) == frozenset()  # 31-44 %: none under half of 38 %
