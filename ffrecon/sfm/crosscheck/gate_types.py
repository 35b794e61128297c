"""A gate's verdict, the gates' result and options, the causes a failed gate names (with their fixes), and the
verdict of a run in which no camera could be checked.
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Collection
from dataclasses import dataclass

from ffrecon.checks import check_number


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
