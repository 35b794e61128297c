"""Verification gates: cheap checks that stop a run before the expensive stages.

Each gate returns a :class:`GateVerdict` with its value, threshold, reason and fix. A failed
registration gate names the likely cause (blur, lack of texture, small parallax, too little overlap)
from the capture checks' per-frame measures (:class:`ffrecon.capture.quality.CaptureQuality`) and from
the verified pairs of the images COLMAP left out (:mod:`ffrecon.sfm.verified_pairs`: their matches
and triangulation angles), so the user knows what to change; the images are not read again. Masks
(``--masks``) that ignore every pixel are named as the cause before anything else (read only when a gate
failed).

A run in which a check was tried and no camera could be checked (COLMAP and the refinement found nothing
to check them with) fails too (:func:`unchecked_verdict`): the model's cameras, unverified, would
otherwise pass as a result. Runs that turn every check off (``--no-colmap --no-refine``) check nothing on
purpose: they pass, the report saying so.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import logging
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass

import numpy as np
import pycolmap

from ffrecon.capture.quality import CaptureQuality
from ffrecon.checks import check_number
from ffrecon.sfm.crosscheck import ColmapResult
from ffrecon.sfm.verified_pairs import ImagePairs, read_image_pairs
from ffrecon.types import Prediction, Skipped

logger = logging.getLogger("ffrecon.sfm")


class GateStatus(enum.Enum):
    PASS = "pass"
    FAIL = "fail"
    SKIPPED = "skipped"  # nothing to check (e.g. no COLMAP model, no prediction)
    WARN = "warn"  # passes, but something is unchecked (the run ends with exit 0 and says so)


class FailureCause(enum.Enum):
    BLUR = "blur"
    TEXTURE = "texture"
    EXPOSURE = "exposure"
    MIXED_CAMERAS = "mixed_cameras"  # the unregistered photos come from other cameras or zoom settings
    DISCONNECTED = "disconnected"  # several models: groups of photos that share no views
    SMALL_PARALLAX = "small_parallax"  # plenty of verified matches, too little baseline to triangulate
    OVERLAP = "overlap"  # the photos left out share few matches: too little overlap or too wide a baseline
    MASKED = "masked"  # the masks (--masks) ignore every pixel of the photos: nothing is left to match


@dataclass(frozen=True)
class GateVerdict:
    name: str
    status: GateStatus
    value: float | None
    threshold: float | None
    reason: str
    fix: str = ""
    causes: tuple[FailureCause, ...] = ()  # likely causes, most likely first (registration gate)
    # False for a witness's verdict: COLMAP's gates when a model's cameras are judged on their own evidence.
    blocking: bool = True

    @property
    def failed(self) -> bool:
        return self.status is GateStatus.FAIL

    def to_report(self) -> dict:
        return {
            "name": self.name,
            "status": self.status.value,
            "value": self.value,
            "threshold": self.threshold,
            "reason": self.reason,
            "fix": self.fix,
            "causes": [c.value for c in self.causes],
            "blocking": self.blocking,
        }


@dataclass(frozen=True)
class GatesResult:
    verdicts: tuple[GateVerdict, ...]
    forced: bool  # --force: failed gates do not stop the run

    @property
    def failed(self) -> tuple[GateVerdict, ...]:
        """Failed verdicts that stop the run (unless forced); a witness's failures are only reported."""
        return tuple(v for v in self.verdicts if v.failed and v.blocking)

    @property
    def blocking(self) -> bool:
        """Whether a failed gate stops the run: the one place this is decided."""
        return bool(self.failed) and not self.forced


@dataclass(frozen=True, kw_only=True)
class GateOptions:
    min_registration_ratio: float = 0.85
    min_points: int = 100
    min_in_front_ratio: float = 0.99  # observations with the point in front of the camera
    min_cloud_spread: float = 0.01  # p90 point distance from the median point / camera extent
    max_cloud_tail: float = 1000.0  # p99 / p50 of point distances from the median point
    min_depth_conf: float = 1.5
    min_depth_coverage: float = 0.5  # mean share of pixels with confident feed-forward depth
    min_keypoints: int = 300  # without capture measures: fewer median SIFT features = blur or texture
    # A cause is named when this share of the images carries its capture flag ("blur", "texture";
    # thresholds in ffrecon.capture.quality.QualityOptions).
    cause_share: float = 0.3
    # Verified inlier matches from which two photos clearly overlap: 100 is what COLMAP's incremental
    # mapper asks of an initial pair (init_min_num_inliers). A photo COLMAP left out whose best pair shares
    # fewer has too little overlap, or too wide a baseline, with every other photo.
    overlap_matches: int = 100
    # Median triangulation angle (degrees) of a pair's verified matches under which it lacks parallax. A
    # photo left out whose pairs with overlap_matches or more are under this (their median) lacks
    # parallax, not overlap. Measured on such pairs: lund's forward walk 0.4 to 2.6 degrees (with or
    # without EXIF), the wide synthetic scenes 8 to 18 (true focal length) or 26 (COLMAP's guess, 39%
    # long); COLMAP wants 16 of its initial pair and drops points seen under 1.5. Pairs with fewer
    # matches give no angle to trust (their relative pose is often wrong), so they are not asked.
    small_parallax_deg: float = 5.0
    # Bounds on the diagnosis's work: the verified pairs of at most this many photos left out (evenly
    # spread), and the relative poses of each one's best pairs only.
    diagnosis_max_images: int = 50
    diagnosis_max_pairs: int = 5

    def __post_init__(self) -> None:
        check_number(
            "GateOptions.min_registration_ratio", self.min_registration_ratio, low=0, high=1, flag="--min-registration"
        )
        for name in ("min_in_front_ratio", "min_depth_coverage", "cause_share"):
            check_number(f"GateOptions.{name}", getattr(self, name), low=0, high=1)
        for name in ("min_points", "min_keypoints", "overlap_matches"):
            check_number(f"GateOptions.{name}", getattr(self, name), low=0, integer=True)
        for name in ("diagnosis_max_images", "diagnosis_max_pairs"):
            check_number(f"GateOptions.{name}", getattr(self, name), low=1, integer=True)
        check_number("GateOptions.small_parallax_deg", self.small_parallax_deg, low=0, high=180)
        for name in ("min_cloud_spread", "max_cloud_tail", "min_depth_conf"):
            check_number(f"GateOptions.{name}", getattr(self, name), low=0)


_FIXES = {
    FailureCause.BLUR: "the images look blurred: hold the camera steady, use more light or a faster shutter, "
    "and drop blurred frames (for video, keep the sharpest frame of each second)",
    FailureCause.TEXTURE: "the surfaces show too little texture for feature matching: add texture (objects, "
    "posters), light the scene evenly, or accept the feed-forward cameras with --force",
    FailureCause.EXPOSURE: "the exposure changes between photos: lock exposure and white balance while capturing",
    FailureCause.MIXED_CAMERAS: "the photos COLMAP left out come mostly from another camera or zoom setting (another "
    "image size or EXIF focal length) than those it registered; each gets its own camera, which few photos "
    "calibrate poorly: capture with one camera at a fixed zoom, or add more photos from the other camera",
    FailureCause.DISCONNECTED: "COLMAP built several separate models: some photos share no views with the rest; "
    "add photos that bridge the groups",
    FailureCause.SMALL_PARALLAX: "the photos overlap well but their viewpoints barely differ (walking straight "
    "forward, or turning on the spot), so nothing can be triangulated: move sideways between shots, or give a "
    "model (--model) whose cameras can carry the run",
    FailureCause.OVERLAP: "the photos left out share too few matches with any other photo: too little overlap or "
    "too wide a baseline between them and the rest (the view turns or moves too far between shots); take more "
    "photos in between, each sharing about two thirds of its view with the previous one, and move less between shots",
    FailureCause.MASKED: "the masks (--masks) are 0 (ignore) on (nearly) every pixel, so nothing is left to match "
    "or fuse: check the mask polarity: 0 = ignore, 255 = use (invert masks drawn the other way round)",
}

MaskedOut = Callable[[], Collection[str]]  # the frames whose masks ignore (nearly) every pixel, read when asked
# A frame whose mask (--masks) keeps less than this share of its pixels counts as masked out: its photo gives
# no features and no depth, whatever it shows.
MIN_MASK_USE = 0.01


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


def _cloud_checks(rec: pycolmap.Reconstruction, options: GateOptions) -> tuple[float, list[str]]:
    """Share of observations in front of their camera, and the list of problems found."""
    problems = []
    xyz = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
    if len(xyz) < options.min_points:
        problems.append(f"only {len(xyz)} points (< {options.min_points})")
    centers = np.array([rec.image(i).projection_center() for i in rec.reg_image_ids()]).reshape(-1, 3)
    if len(xyz) >= 3:
        dist = np.linalg.norm(xyz - np.median(xyz, axis=0), axis=1)
        cam_extent = float(np.linalg.norm(np.ptp(centers, axis=0))) if len(centers) >= 2 else 0.0
        spread = np.percentile(dist, 90) / cam_extent if cam_extent > 0 else np.inf
        if spread < options.min_cloud_spread:
            problems.append(f"the cloud is degenerate: 90% of points lie within {spread:.2%} of the camera extent")
        p50 = np.percentile(dist, 50)
        tail = np.percentile(dist, 99) / p50 if p50 > 0 else 0.0
        if tail > options.max_cloud_tail:
            problems.append(f"the cloud explodes: the farthest 1% of points are {tail:.0f}x the median distance away")
    in_front = total = 0
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        pose = np.asarray(image.cam_from_world().matrix())
        ids = [p.point3D_id for p in image.points2D if p.has_point3D()]
        if not ids:
            continue
        pts = np.array([rec.points3D[i].xyz for i in ids])
        z = pts @ pose[2, :3] + pose[2, 3]
        in_front += int((z > 0).sum())
        total += len(z)
    ratio = in_front / total if total else 0.0
    if total and ratio < options.min_in_front_ratio:
        problems.append(f"{1 - ratio:.1%} of observations see their point behind the camera")
    return ratio, problems


def sparse_cloud_gate(
    rec: pycolmap.Reconstruction | None, options: GateOptions, *, label: str = "COLMAP"
) -> GateVerdict:
    if rec is None or rec.num_reg_images() == 0:
        return GateVerdict(
            "sparse_cloud", GateStatus.SKIPPED, None, options.min_in_front_ratio, f"no {label} model to check"
        )
    ratio, problems = _cloud_checks(rec, options)
    if problems == problems[:1] and rec.num_points3D() < options.min_points:  # sound but thin, e.g. two small photos
        return GateVerdict(
            "sparse_cloud",
            GateStatus.FAIL,
            ratio,
            options.min_in_front_ratio,
            f"the {label} sparse cloud is too thin to trust: {problems[0]}",
            "too few points triangulate: use the photos at full resolution, add photos taken with more sideways "
            "movement between them, or run with --force to continue anyway",
        )
    if problems:
        return GateVerdict(
            "sparse_cloud",
            GateStatus.FAIL,
            ratio,
            options.min_in_front_ratio,
            f"the {label} sparse cloud looks wrong: " + "; ".join(problems),
            "the reconstruction is unreliable: check the images for moving objects, reflections "
            "or repeated patterns, or run with --force to continue anyway",
        )
    return GateVerdict(
        "sparse_cloud",
        GateStatus.PASS,
        ratio,
        options.min_in_front_ratio,
        f"{rec.num_points3D()} points, {ratio:.1%} of observations in front of their camera, extent plausible",
    )


def depth_coverage_gate(
    prediction: Prediction | None, options: GateOptions, *, masked_out: MaskedOut | None = None
) -> GateVerdict:
    """Mean share of pixels with confident feed-forward depth; on failure, masks that ignore every pixel of
    ``cause_share`` of the frames or more (``masked_out``) are named as the cause."""
    if prediction is None or len(prediction) == 0:
        return GateVerdict(
            "depth_coverage", GateStatus.SKIPPED, None, options.min_depth_coverage, "no feed-forward prediction"
        )
    shares = np.array([prediction.valid_mask(i, options.min_depth_conf).mean() for i in range(len(prediction))])
    coverage = float(shares.mean())
    worst = prediction.names[int(np.argmin(shares))]
    reason = (
        f"{coverage:.0%} of pixels have feed-forward depth with confidence >= {options.min_depth_conf:g} "
        f"(lowest: {worst}, {shares.min():.0%})"
    )
    if coverage >= options.min_depth_coverage:
        return GateVerdict("depth_coverage", GateStatus.PASS, coverage, options.min_depth_coverage, reason)
    fix = (
        "the model is unsure of most of the scene: check that the images show one static scene, "
        "try another model, or run with --force"
    )
    causes: tuple[FailureCause, ...] = ()
    masked = set(masked_out() if masked_out is not None else ()) & set(prediction.names)
    if len(masked) >= max(options.cause_share * len(prediction), 1):
        reason += f"; the masks ignore every pixel of {len(masked)} of {len(prediction)} frames"
        fix = _FIXES[FailureCause.MASKED] + ("" if len(masked) == len(prediction) else f"; else {fix}")
        causes = (FailureCause.MASKED,)
    return GateVerdict("depth_coverage", GateStatus.FAIL, coverage, options.min_depth_coverage, reason, fix, causes)


UNCHECKED_FIX = (
    "the photos give too few matches to check any camera (blank, dark, blurred or textureless photos, or too little "
    "overlap between them): retake them with more light, texture and overlap, or run with --force to keep the "
    "model's cameras, marked unchecked"
)


def unchecked_verdict(num_cameras: int, tried: str, *, fix: str = UNCHECKED_FIX) -> GateVerdict:
    """The failing (blocking) ``checked_share`` verdict of a run that tried to check its cameras and checked none:
    ``tried`` says what ran and what it found (e.g. "COLMAP registered 0 of 6 images").

    >>> unchecked_verdict(6, "COLMAP registered 0 of 6 images").reason
    'no camera could be checked: COLMAP registered 0 of 6 images; all 6 final cameras are unverified'
    """
    reason = f"no camera could be checked: {tried}; all {num_cameras} final cameras are unverified"
    return GateVerdict("checked_share", GateStatus.FAIL, 0.0, None, reason, fix)


def evaluate_gates(
    *,
    colmap: ColmapResult | None,
    prediction: Prediction | None,
    quality: CaptureQuality | None = None,
    options: GateOptions = GateOptions(),
    colmap_skipped: str = "",
    masked_out: MaskedOut | None = None,
) -> list[GateVerdict]:
    """Registration, sparse-cloud sanity (COLMAP model) and feed-forward depth coverage, in that order.

    ``quality`` (the capture stage's measures and flags) lets a failed registration gate name blur
    or lack of texture as the cause, ``masked_out`` masks that ignore every pixel (called once, and only
    when a gate failed). Without ``colmap`` the first two are SKIPPED, saying why the cross-check did not
    run when ``colmap_skipped`` gives the reason.
    """
    masked_out = functools.cache(masked_out) if masked_out is not None else None
    verdicts = []
    if colmap is None:
        why = f"COLMAP cross-check not run: {colmap_skipped}" if colmap_skipped else "COLMAP cross-check not run"
        threshold = options.min_registration_ratio
        verdicts.append(GateVerdict("registration", GateStatus.SKIPPED, None, threshold, why))
        verdicts.append(GateVerdict("sparse_cloud", GateStatus.SKIPPED, None, options.min_in_front_ratio, why))
    else:
        verdicts.append(registration_gate(colmap, options, quality=quality, masked_out=masked_out))
        verdicts.append(sparse_cloud_gate(colmap.reconstruction, options))
    verdicts.append(depth_coverage_gate(prediction, options, masked_out=masked_out))
    for v in verdicts:
        (logger.warning if v.failed else logger.info)("gate %s: %s - %s", v.name, v.status.value, v.reason)
    return verdicts


def run_gates(
    *,
    colmap: ColmapResult | None,
    prediction: Prediction | None,
    quality: CaptureQuality | None,
    options: GateOptions = GateOptions(),
    force: bool = False,
    witness: bool = False,
    colmap_skipped: str = "",
    masked_out: MaskedOut | None = None,
    unchecked: GateVerdict | None = None,
) -> GatesResult:
    """The gates stage: :func:`evaluate_gates`, and whether a failure stops the run (not with ``force``).

    ``witness``: COLMAP is a witness (a model's cameras will be judged on their own evidence, see
    :mod:`ffrecon.sfm.evidence`): its registration and sparse-cloud verdicts are reported, not blocking.
    ``colmap_skipped``: why the cross-check did not run (given when ``colmap`` is None). ``unchecked``: the
    verdict of a run that checks its cameras no further and checked none (:func:`unchecked_verdict`), added.
    """
    verdicts = evaluate_gates(
        colmap=colmap,
        prediction=prediction,
        quality=quality,
        options=options,
        colmap_skipped=colmap_skipped,
        masked_out=masked_out,
    )
    if witness:
        colmap_gates = ("registration", "sparse_cloud")
        verdicts = [dataclasses.replace(v, blocking=v.name not in colmap_gates) for v in verdicts]
    if unchecked is not None:
        logger.warning("gate %s: %s - %s", unchecked.name, unchecked.status.value, unchecked.reason)
        verdicts.append(unchecked)
    result = GatesResult(tuple(verdicts), force)
    if result.failed and force:
        names = ", ".join(v.name for v in result.failed)
        logger.warning("continuing despite %d failed gates (forced): %s", len(result.failed), names)
    return result


def gate_poses(
    quality: CaptureQuality | None,
    prediction: Prediction | None,
    colmap: ColmapResult | Skipped,
    options: GateOptions,
    *,
    force: bool,
    judged: bool = True,
    masked_out: MaskedOut | None = None,
) -> GatesResult:
    """The run's gates on the capture and the COLMAP cross-check. With a model (``prediction``), COLMAP is a
    witness: the final cameras are judged on their own evidence instead (:mod:`ffrecon.sfm.evidence`).

    ``judged``: the refinement will judge the model's cameras (False: ``--no-refine``). When it will not,
    COLMAP is the only check: if it registered fewer than two images, no camera could be checked, and the
    run fails (:func:`unchecked_verdict`). ``masked_out``: see :func:`evaluate_gates`.
    """
    unchecked = None
    if prediction is not None and not judged and isinstance(colmap, ColmapResult) and colmap.num_registered < 2:
        tried = f"COLMAP registered {colmap.num_registered} of {len(colmap.names)} images and --no-refine is given"
        fix = f"drop --no-refine: the refinement checks the cameras on their own image matches; else {UNCHECKED_FIX}"
        unchecked = unchecked_verdict(len(prediction), tried, fix=fix)
    return run_gates(
        colmap=colmap if isinstance(colmap, ColmapResult) else None,
        prediction=prediction,
        quality=quality,
        options=options,
        force=force,
        witness=prediction is not None,
        colmap_skipped=colmap.reason if isinstance(colmap, Skipped) else "",
        masked_out=masked_out,
        unchecked=unchecked,
    )
