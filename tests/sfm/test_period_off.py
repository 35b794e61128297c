"""On look-alike surfaces a refinement that moved many frames far from the model is set aside as a whole
(:func:`ffrecon.sfm.verify.frames._period_off`, issue 39). Held-out object seed 219 (repeated tile, drift, 50-90 deg
apart): the adjustment moved 4 of 8 frames 12-20 deg, each left out as a period off, and the other 4, kept at their
refined poses, ended 5.8-8.6 deg off (the model's median 2.1). The frames are then all unchecked at the model's
cameras, and the final cameras are the model's."""

from types import SimpleNamespace

import numpy as np

from ffrecon.sfm.verify.frames import _period_off
from ffrecon.sfm.verify.verdicts import CameraEvidence, CameraStatus, EvidenceOptions

NAMES = tuple(f"frame_{k:03d}.png" for k in range(8))


def _case(changes, lookalike=True):
    refine = SimpleNamespace(guidance=SimpleNamespace(lookalike=lookalike), registered=np.ones(8, bool), dense=None)
    per_image = tuple(
        CameraEvidence(n, CameraStatus.CONTRADICTED if c > 10 else CameraStatus.GUIDED, "", c)
        for n, c in zip(NAMES, changes)
    )
    return per_image, refine


def test_many_frames_a_period_off_set_the_refinement_aside():
    per_image, refine = _case([20.3, 18.4, 1.0, 2.0, 1.5, 20.6, 19.2, 2.2])
    judged, why, share = _period_off(per_image, refine, EvidenceOptions())
    assert share == 0.5
    assert "4 of its 8 frames" in why and "keeps the model's camera" in why
    assert all(e.status is CameraStatus.UNCHECKED for e in judged)


def test_a_corrected_frame_and_one_more_do_not():
    """Room seed 221, frame 1 25 deg off: it and one more frame moved, the others ended within 0.1 deg."""
    per_image, refine = _case([24.0, 12.0, 1.0, 2.0, 1.5, 2.6, 1.2, 2.2])
    assert _period_off(per_image, refine, EvidenceOptions())[:2] == (per_image, "")


def test_off_lookalike_surfaces_nothing_is_set_aside():
    per_image, refine = _case([20.3, 18.4, 1.0, 2.0, 1.5, 20.6, 19.2, 2.2], lookalike=False)
    assert _period_off(per_image, refine, EvidenceOptions())[:2] == (per_image, "")
