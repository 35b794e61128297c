"""The registration gate on COLMAP's model, and the likely cause of a failure: the capture checks' measures and
the verified pairs of the images COLMAP left out (:mod:`ffrecon.sfm.verified_pairs`).
"""

from __future__ import annotations

import logging
from collections.abc import Collection, Sequence

import numpy as np

from ffrecon.capture.quality import CaptureQuality
from ffrecon.sfm.crosscheck.gate_types import _FIXES, FailureCause, GateOptions, GateStatus, GateVerdict, MaskedOut
from ffrecon.sfm.crosscheck.run import ColmapResult
from ffrecon.sfm.verified_pairs import ImagePairs, read_image_pairs

logger = logging.getLogger("ffrecon.sfm")


def diagnose_registration(
    quality: CaptureQuality | None,
    names: Sequence[str],
    median_keypoints: int,
    options: GateOptions,
    *,
    left_out: Sequence[ImagePairs] | None = None,
    median_verified_matches: int = 0,
    num_models: int = 1,
    camera_groups: np.ndarray | None = None,
    registered: np.ndarray | None = None,
    masked_out: Collection[str] = (),
) -> tuple[FailureCause, ...]:
    """Likely causes of poor registration of ``names``, most likely first.

    Masks that ignore every pixel of ``cause_share`` of the images or more (``masked_out``: their names)
    come first and alone: the photos were never seen, so nothing else about them can be told.

    Blur, lack of texture and exposure drift come from the capture flags on those images (blur
    lowers the edge sharpness; a textureless image has a low mean gradient but sharp edges).
    Without capture measures for them, few SIFT features point at blur or texture. When the images
    look fine, the cameras and matches decide: when the photos come from several cameras
    (``camera_groups``, ``[N]`` int) and most unregistered ones (``registered``, ``[N]`` bool) are not of
    the camera most registered ones are of, mixed cameras; several models mean disconnected groups;
    then the verified pairs of the images COLMAP left out (``left_out``, see :func:`_match_causes`)
    tell small parallax from too little overlap or too wide a baseline. Without them (no database),
    ``median_verified_matches`` (the images left out, per verified pair) stands in, angles unknown:
    many mean small parallax. When nothing else is named: too little overlap or too wide a baseline.
    """
    if len(set(names) & set(masked_out)) >= max(options.cause_share * len(names), 1):
        return (FailureCause.MASKED,)
    measured = set(names) & set(quality.names) if quality is not None else set()
    if not measured and median_keypoints < options.min_keypoints:
        return (FailureCause.BLUR, FailureCause.TEXTURE)
    causes = []
    for cause in (FailureCause.BLUR, FailureCause.TEXTURE, FailureCause.EXPOSURE):
        if measured and len(measured & set(quality.flagged(cause.value))) >= options.cause_share * len(measured):
            causes.append(cause)
    if causes:
        return tuple(causes)
    if _mixed_cameras(camera_groups, registered):
        causes.append(FailureCause.MIXED_CAMERAS)
    if num_models > 1:
        causes.append(FailureCause.DISCONNECTED)
    causes += _match_causes(left_out, median_verified_matches, options)
    return tuple(causes) or (FailureCause.OVERLAP,)


def _match_causes(
    left_out: Sequence[ImagePairs] | None, median_verified_matches: int, options: GateOptions
) -> list[FailureCause]:
    """Small parallax and too little overlap (or too wide a baseline), from the images COLMAP left out.

    Each image left out votes (:func:`_match_vote`); a cause is named when at least ``cause_share``
    of them vote for it, the one with more votes first.

    >>> pairs = [ImagePairs("a.jpg", np.array([14, 9]), np.array([35.0, 41.0]))]
    >>> _match_causes(pairs, 0, GateOptions())
    [<FailureCause.OVERLAP: 'overlap'>]
    """
    if left_out is None:
        return [FailureCause.SMALL_PARALLAX] if median_verified_matches >= options.overlap_matches else []
    votes = [_match_vote(pairs, options) for pairs in left_out]
    named = [
        cause
        for cause in (FailureCause.SMALL_PARALLAX, FailureCause.OVERLAP)
        if votes.count(cause) and votes.count(cause) >= options.cause_share * len(votes)
    ]
    return sorted(named, key=lambda cause: -votes.count(cause))


def _match_vote(pairs: ImagePairs, options: GateOptions) -> FailureCause | None:
    """What one image's verified pairs say: no pair with ``overlap_matches`` is too little overlap or too wide a
    baseline; such pairs under ``small_parallax_deg`` (their median angle; none measured counts as under) are
    small parallax; such pairs with parallax explain nothing (None)."""
    well = pairs.num_inliers >= options.overlap_matches
    if not well.any():
        return FailureCause.OVERLAP
    angles = pairs.tri_angle_deg[well]
    angles = angles[np.isfinite(angles)]
    if not len(angles) or float(np.median(angles)) < options.small_parallax_deg:
        return FailureCause.SMALL_PARALLAX
    return None


def _mixed_cameras(groups: np.ndarray | None, registered: np.ndarray | None) -> bool:
    """Several camera groups; the registered images' main group registers at least twice as well as the others
    together, and at least half of the unregistered images lie outside it."""
    if (
        groups is None
        or registered is None
        or len(set(groups.tolist())) < 2
        or registered.all()
        or not registered.any()
    ):
        return False
    main = groups == int(np.bincount(groups[registered]).argmax())
    ratio_main, ratio_rest = registered[main].mean(), registered[~main].mean()
    return bool(ratio_main >= 2 * ratio_rest and np.mean(~main[~registered]) >= 0.5)


_LIKELY = {
    FailureCause.BLUR: "blur",
    FailureCause.TEXTURE: "lack of texture",
    FailureCause.EXPOSURE: "exposure changes",
    FailureCause.MIXED_CAMERAS: "photos from several cameras or zoom settings",
    FailureCause.DISCONNECTED: "groups of photos that share no views",
    FailureCause.SMALL_PARALLAX: "too little parallax (viewpoints too alike)",
    FailureCause.OVERLAP: "too little overlap or too wide a baseline between the photos left out and the rest",
    FailureCause.MASKED: "masks that ignore every pixel of the photos (0 = ignore)",
}


def registration_gate(
    colmap: ColmapResult,
    options: GateOptions,
    *,
    quality: CaptureQuality | None = None,
    masked_out: MaskedOut | None = None,
) -> GateVerdict:
    """Share of images COLMAP registered; on failure the likely causes, from ``masked_out`` (masks that ignore
    every pixel), from ``quality`` when given and from the verified pairs of the images left out (read from
    COLMAP's database)."""
    ratio = colmap.registration_ratio
    if ratio >= options.min_registration_ratio:
        return GateVerdict(
            "registration",
            GateStatus.PASS,
            ratio,
            options.min_registration_ratio,
            f"COLMAP registered {colmap.num_registered} of {len(colmap.names)} images",
        )
    kps = int(np.median(colmap.features.num_keypoints)) if len(colmap.names) else 0
    left_out = _left_out_pairs(colmap, options)
    matches = _left_out_matches_per_pair(colmap)
    causes = diagnose_registration(
        quality,
        colmap.names,
        kps,
        options,
        left_out=left_out,
        median_verified_matches=matches,
        num_models=colmap.num_models,
        camera_groups=colmap.camera_groups,
        registered=colmap.registered,
        masked_out=masked_out() if masked_out is not None else (),
    )
    reason = (
        f"COLMAP registered only {colmap.num_registered} of {len(colmap.names)} images ({ratio:.0%} < "
        f"{options.min_registration_ratio:.0%}); median {kps} SIFT features per image, "
        f"{colmap.features.num_pairs_verified} verified image pairs"
        f"{f', {colmap.num_models} separate models' if colmap.num_models > 1 else ''}; "
        f"{_left_out_text(left_out, matches, len(colmap.names) - colmap.num_registered, options)}; "
        f"likely cause: {' or '.join(_LIKELY[c] for c in causes)}"
    )
    return GateVerdict(
        "registration",
        GateStatus.FAIL,
        ratio,
        options.min_registration_ratio,
        reason,
        "; ".join(_FIXES[c] for c in causes),
        causes,
    )


def _left_out_pairs(colmap: ColmapResult, options: GateOptions) -> tuple[ImagePairs, ...] | None:
    """The verified pairs of the images COLMAP left out, or None when its database cannot be read."""
    names = [name for name, done in zip(colmap.names, colmap.registered) if not done]
    try:
        return read_image_pairs(
            colmap.database_path,
            names,
            max_pairs=options.diagnosis_max_pairs,
            max_images=options.diagnosis_max_images,
        )
    except (OSError, RuntimeError) as error:  # pycolmap raises RuntimeError on a database it cannot read
        logger.warning("registration diagnosis from matches per image only: %s", error)
        return None


def _left_out_matches_per_pair(colmap: ColmapResult) -> int:
    """Median over the images COLMAP left out of their verified matches per verified pair (0 without any)."""
    features, left = colmap.features, ~colmap.registered
    if not left.any():
        return 0
    per_pair = features.num_inlier_matches[left] / np.maximum(features.num_verified_pairs[left], 1)
    return int(np.median(per_pair))


def _left_out_text(left_out: Sequence[ImagePairs] | None, matches: int, num_left: int, options: GateOptions) -> str:
    """What the verified pairs of the images left out show, for the gate's reason."""
    if left_out is None:
        return f"the {num_left} images left out share a median {matches} verified matches per verified pair"
    best = int(np.median([pairs.best_inliers for pairs in left_out])) if left_out else 0
    text = f"the {num_left} images left out share a median {best} verified matches with their best neighbour"
    angles = [
        float(np.nanmedian(pairs.tri_angle_deg[well]))
        for pairs in left_out
        if (well := (pairs.num_inliers >= options.overlap_matches) & np.isfinite(pairs.tri_angle_deg)).any()
    ]
    if angles:
        text += (
            f", and their pairs with {options.overlap_matches} or more triangulate at a median angle of "
            f"{np.median(angles):.1f} deg"
        )
    return text
