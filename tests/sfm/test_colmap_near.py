"""A refined frame COLMAP registered a few degrees away is kept, not confirmed (EvidenceOptions.max_confirm_gap_deg).

Found on object seed 322 (scale errors, tools/sweep_families.py): a frame refined 6.5 deg from the truth on weak
dense links was 4.3 deg from COLMAP's after the alignment over COLMAP's three frames, under the 5-deg disagreement,
and was called confirmed by COLMAP.
"""

import numpy as np

from ffrecon.sfm.verify.frames import _colmap_word
from ffrecon.sfm.verify.verdicts import CameraStatus, EvidenceOptions, FrameVerdict


def test_a_gap_beyond_the_confirmation_bar_but_short_of_a_disagreement_is_not_a_confirmation():
    options = EvidenceOptions()
    close = _colmap_word(None, True, 1.2, options)
    assert close.agrees and not close.near and close.why == "COLMAP's pose agrees"
    near = _colmap_word(None, True, 4.3, options)
    assert near.agrees and near.near and "4.3 deg" in near.why and "not confirmed" in near.why
    assert not _colmap_word(None, False, float("nan"), options).near  # no gap measured: COLMAP's word stands
    off = _colmap_word("rotation 12.0 deg > 5", True, 12.0, options)
    assert not off.agrees  # a disagreement stays one (the frame is left out)
    assert CameraStatus.COLMAP_NEAR.kept and CameraStatus.COLMAP_NEAR.verdict is FrameVerdict.UNCHECKED
    assert not _colmap_word(None, True, 2.0, EvidenceOptions(max_confirm_gap_deg=2.0)).near  # at the bar: confirmed
    assert np.isfinite(options.max_confirm_gap_deg) and options.max_confirm_gap_deg < 5.0
