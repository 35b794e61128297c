"""The model's own signs against a frame's camera, beside the photos' (:mod:`ffrecon.sfm.verify.unmatched`): its depth
placed with its camera disagreeing with the other frames' depth, and dense tracks from its prediction that find few
of their corners (:mod:`ffrecon.sfm.refine.dense`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ffrecon.geometry.overlap import view_agreement
from ffrecon.sfm.refine.options import RefineResult
from ffrecon.sfm.verify.verdicts import CameraEvidence, CameraStatus, EvidenceOptions
from ffrecon.types import Prediction


@dataclass(frozen=True)
class DepthShares:
    """The frames the model's depth judges (nothing else checks them) and how their depth agrees with the others':
    ``seen[name]`` the share of its points landing in the other frames' views (summed), ``ratio[name]`` the share
    of those agreeing with their depth over the median frame's (nan where none lands)."""

    seen: dict[str, float]
    ratio: dict[str, float]
    typical: float  # the median frame's share

    def below(self, ratio: float, min_seen: float) -> frozenset[str]:
        """The frames whose points land in the others' views (``min_seen`` at least) and agree with their depth at
        most ``ratio`` times as often as the median frame's."""
        return frozenset(n for n, r in self.ratio.items() if self.seen[n] >= min_seen and r <= ratio)


def _depth_shares(per_image, depth: Prediction, limit: float, *, every: bool = False) -> DepthShares | None:
    """:class:`DepthShares` of the frames keeping the model's camera with no verified pair agreeing with it (none,
    or pairs disputing it); with ``every``, of each frame keeping the model's camera (the refinement set aside as a
    whole, whatever it moved a frame). None where there is nothing to judge or no median frame."""
    judged = [
        k
        for k, e in enumerate(per_image)
        if (
            e.status is CameraStatus.UNCHECKED
            and (every or not (np.isfinite(e.correction_deg) and e.correction_deg <= limit))
        )
        or e.pose_in_doubt
        or e.status is CameraStatus.CORRECTED  # for _model_camera_kept
    ]
    if not judged or depth.depth is None or len(per_image) < 3:
        return None
    # the median frame from an even sample of at most 16 (the cost grows with the frames judged, not N^2)
    sample = np.unique(np.linspace(0, len(per_image) - 1, min(len(per_image), 16)).astype(int)).tolist()
    frames = sorted(set(judged) | set(sample))
    seen, agreeing = view_agreement(depth, frames).T
    share = dict(zip(frames, np.divide(agreeing, seen, out=np.full(len(frames), np.nan), where=seen > 0)))
    typical = [share[k] for k in sample if np.isfinite(share[k])]
    if not typical:
        return None
    typical = float(np.median(typical))
    names = [per_image[k].name for k in judged]
    seen = dict(zip(frames, seen))
    return DepthShares(
        {n: float(seen[k]) for n, k in zip(names, judged)},
        {n: float(share[k] / typical) if typical > 0 else np.nan for n, k in zip(names, judged)},
        typical,
    )


def _depth_misfits(per_image, shares: DepthShares | None, options: EvidenceOptions):
    """``per_image`` with the frames nothing checks that the model's own depth contradicts left out
    (:attr:`EvidenceOptions.depth_misfit_ratio`, :func:`ffrecon.geometry.overlap.view_agreement`), the frames
    judged and their shares in ``shares`` (:func:`_depth_shares`).

    On the repeated-tile object (held-out seeds 235-247) a frame 25 deg off had no verified match (the matches
    guided by its camera found none) and no photometric verdict, and was exported unchecked; its depth, placed
    with its camera, agreed with the other frames' depth on 1-9 % of the points landing in their views, the
    median frame on 30-60 %."""
    if shares is None:
        return per_image
    misfits = shares.below(options.depth_misfit_ratio, options.min_view_share)
    out = list(per_image)
    for k, e in enumerate(out):
        if e.name not in misfits or e.status is not CameraStatus.UNCHECKED:
            continue
        ratio = shares.ratio[e.name]
        unmatched = e.why.removesuffix("the model's camera is kept").rstrip(":; ")
        why = (
            f"{unmatched}; but the model's depth of it, placed with its camera, agrees with the other frames' depth "
            f"on {ratio * shares.typical:.0%} of its points in their views (the median frame: {shares.typical:.0%}): "
            "its camera is contradicted by the model's own geometry: left out"
        )
        out[k] = CameraEvidence(e.name, CameraStatus.DEPTH_MISFIT, why, e.correction_deg)
    return tuple(out)


def _depth_doubted(shares: DepthShares | None, options: EvidenceOptions) -> frozenset[str]:
    """The frames whose depth, placed with their camera, agrees with the others' at most
    :attr:`EvidenceOptions.depth_doubt_ratio` times as often as the median frame's (points in their views)."""
    return frozenset() if shares is None else shares.below(options.depth_doubt_ratio, options.min_view_share)


def _dense_misfits(per_image, refine: RefineResult, options: EvidenceOptions):
    """``per_image`` with the unchecked frames that dense tracking from the model's prediction contradicts left
    out (:attr:`EvidenceOptions.min_dense_predicted`, :attr:`EvidenceOptions.dense_misfit_ratio`).

    Dense correspondences are tracked from where the model's depth and cameras put a frame's corners in its
    overlapping frames, refined within a small window (:mod:`ffrecon.sfm.refine.dense`). A camera a few degrees
    off leaves them within the window; one 25 deg off puts them far from their match, and almost none survive
    the checks and the pair's verification. The frames are judged one at a time, the worst first, each on its
    pairs with frames not yet left out: a pair with a frame 25 deg off fails for its partner too (room seed 203,
    frame 6 off: frame 5, 3.2 deg off in the model, had tracked only with frame 6 and its other failing pair)."""
    dense = refine.dense
    if dense is None or not dense.pairs:
        return per_image
    out, left = list(per_image), set()
    for _ in range(len(out)):
        shares = _dense_shares(dense.pairs, left, options.min_dense_predicted)
        judged = [k for k, e in enumerate(out) if e.status is CameraStatus.UNCHECKED and e.name in shares]
        if not judged:
            break
        k = min(judged, key=lambda k: (shares[out[k].name][0], -shares[out[k].name][1]))  # ties: the most tried
        e, (share, tried, kept) = out[k], shares[out[k].name]
        typical = _others_median(shares, e.name)
        if typical <= 0 or share > options.dense_misfit_ratio * typical:
            break
        said = e.why.removesuffix("the model's camera is kept").rstrip(":; ")
        why = (
            f"{said}; but dense tracking from the model's prediction verified {kept} of the {tried} corners it put "
            f"inside the frames it overlaps ({share:.0%}; the other frames tracked: {typical:.0%}, median): its "
            "camera is not where the model says, left out"
        )
        out[k] = CameraEvidence(e.name, CameraStatus.CONTRADICTED, why, e.correction_deg)
        left.add(e.name)
    return tuple(out)


def _dense_doubted(refine: RefineResult, options: EvidenceOptions) -> frozenset[str]:
    """The frames whose dense tracks (at least :attr:`EvidenceOptions.min_dense_doubt_predicted` corners tried)
    verified at most :attr:`EvidenceOptions.dense_doubt_ratio` times the median share of the others (two at least):
    a weak sign, counted beside a photometric one."""
    if refine.dense is None or not refine.dense.pairs:
        return frozenset()
    shares = _dense_shares(refine.dense.pairs, set(), options.min_dense_doubt_predicted)
    return frozenset(
        name
        for name, (share, _, _) in shares.items()
        if (typical := _others_median(shares, name)) > 0 and share <= options.dense_doubt_ratio * typical
    )


def _others_median(shares: dict[str, tuple[float, int, int]], name: str) -> float:
    """The median share verified of the frames in ``shares`` other than ``name`` (0 with fewer than two)."""
    others = [v[0] for n, v in shares.items() if n != name]
    return float(np.median(others)) if len(others) >= 2 else 0.0


def _dense_shares(pairs, left: set[str], min_predicted: int) -> dict[str, tuple[float, int, int]]:
    """Per frame, over its tracked pairs with frames not in ``left``: (share verified, corners predicted,
    verified), for the frames with at least ``min_predicted`` predicted."""
    tried: dict[str, int] = {}
    kept: dict[str, int] = {}
    for a, b, predicted, verified in pairs:
        if a in left or b in left:
            continue
        for name in (a, b):
            tried[name] = tried.get(name, 0) + predicted
            kept[name] = kept.get(name, 0) + verified
    return {n: (kept[n] / t, t, kept[n]) for n, t in tried.items() if t >= min_predicted and n not in left}
