"""Bundle adjustment seeded by the feed-forward cameras.

Only the pairs that the feed-forward geometry says overlap are matched (SIFT, COLMAP's verification);
tracks are triangulated with the feed-forward cameras, then refined by bundle adjustment in two
passes: a coarse pass with tolerances wide enough for feed-forward pose errors and a robust loss, then
a fresh triangulation with the coarse result and COLMAP's usual tolerances. Frames that end up
with too few features, matches or observations, or held to the others only by weak links or links
the model contradicts (``sfm/links.py``), are flagged and kept out; the rest are refined.
The result is expressed in the prediction's world frame (Sim(3)-aligned to its camera centres).
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from ffrecon.capture import Capture
from ffrecon.checks import check_number
from ffrecon.colmap_io import (
    cam_from_world_by_name,
    cameras_by_name,
    pinhole_to_colmap,
    reconstruction_from_cameras,
    write_reconstruction,
)
from ffrecon.errors import InputError
from ffrecon.geometry.alignment import Sim3
from ffrecon.geometry.metrics import aligned_rotation_errors_deg
from ffrecon.geometry.overlap import OverlapGraph, OverlapOptions, overlap_graph
from ffrecon.geometry.undistort import NO_DISTORTION, opencv_coefficients
from ffrecon.sfm.bundle import BundleOptions, BundleSummary, refine_tracks, sim3_to_ff_frame
from ffrecon.sfm.crosscheck import ColmapResult
from ffrecon.sfm.dense import DenseOptions, DenseStats, add_dense_evidence, short_frames
from ffrecon.sfm.features import (
    CameraModel,
    FeatureStats,
    SiftOptions,
    colmap_log_level,
    copy_features,
    copy_verified_matches,
    create_database,
    extract_sift,
    feature_stats,
    match_pairs,
    set_database_cameras,
    verify_pairs,
    write_pairs,
)
from ffrecon.sfm.guided import GuidanceOptions, GuidanceStats, MatchGuidance, filter_matches, guided_matches
from ffrecon.sfm.links import LinkOptions, detached_frames
from ffrecon.sfm.relocalize import Relocalized, RelocalizeOptions, reach_matrix, relocalize, with_poses
from ffrecon.sfm.screen import ScreenOptions, Suspect, drop_contradicting_pairs, reseeded, screen_rotations
from ffrecon.timing import StageTimer, Timings
from ffrecon.types import PinholeCamera, Prediction, RunMode, Skipped
from ffrecon.validate import validate_prediction

logger = logging.getLogger("ffrecon.sfm")


# Quick mode's refinement (RefineOptions.quick); measured in docs/pipeline.md, "Quick mode".
QUICK_SIFT = SiftOptions(first_octave=0, upsample_below_px=500, max_image_size=1600, max_num_features=4096)
QUICK_OVERLAP = OverlapOptions(max_pairs_per_image=4)
QUICK_BUNDLE = BundleOptions(max_refinements=1, fine_function_tolerance=1e-6)


class RefineStatus(enum.Enum):
    SUCCESS = "success"  # every frame refined
    PARTIAL = "partial"  # some frames flagged and kept out, the others refined
    FAILED = "failed"  # fewer than two frames could be refined: the feed-forward cameras are returned


class WeakReason(enum.Enum):
    FEW_FEATURES = "few_features"  # too few SIFT keypoints (textureless, blurred, dark)
    FEW_MATCHES = "few_matches"  # features, but too few verified matches with overlapping frames
    FEW_OBSERVATIONS = "few_observations"  # too few triangulated observations survive refinement
    WEAK_LINK = "weak_link"  # held to the other refined frames only by weak links or ones the model contradicts


@dataclass(frozen=True)
class WeakFrame:
    name: str
    reason: WeakReason
    value: int  # keypoints, verified matches or observations
    threshold: int

    def describe(self) -> str:
        what = {
            WeakReason.FEW_FEATURES: "SIFT keypoints",
            WeakReason.FEW_MATCHES: "verified matches",
            WeakReason.FEW_OBSERVATIONS: "triangulated observations",
            WeakReason.WEAK_LINK: "3D points shared over a link the model agrees with",
        }[self.reason]
        return f"{self.name}: {self.value} {what} (< {self.threshold}); kept out of the refinement"


@dataclass(frozen=True, kw_only=True)
class RefineOptions:
    enabled: bool = True  # False: the stage is skipped (and the report says so)
    overlap: OverlapOptions = OverlapOptions()
    sift: SiftOptions = SiftOptions()
    bundle: BundleOptions = BundleOptions()
    guidance: GuidanceOptions = GuidanceOptions()
    dense: DenseOptions = DenseOptions()  # model-guided correspondences for the frames SIFT leaves short
    # Frames the first adjustment leaves out placed again from their neighbours' renderings (with dense evidence)
    relocalize: RelocalizeOptions = RelocalizeOptions()
    # Frames held to the others only by weak links, or by links the model contradicts, are left out (sfm/links.py)
    links: LinkOptions = LinkOptions()
    # Frames whose verified pairs agree on a rotation far from the model's start the adjustment from it
    screen: ScreenOptions = ScreenOptions()
    reuse_features_from: Path | None = None  # a COLMAP database with SIFT of the same images (the cross-check's)
    single_camera: bool = True  # one shared camera (median feed-forward intrinsics) if all images share a size
    square_pixels: bool = True  # one focal length per camera (fx = fy)
    min_features: int = 100
    min_matches: int = 50  # verified matches summed over the frame's pairs
    min_observations: int = 40
    seed: int = 0
    # With given poses (--poses): the adjustment keeps the camera centres near them, with this std (a fraction
    # of the extent of the centres), instead of letting the feed-forward ones move freely.
    given_pose_std: float = 0.002

    def __post_init__(self) -> None:
        for name in ("min_features", "min_matches", "min_observations"):
            check_number(f"RefineOptions.{name}", getattr(self, name), low=0, integer=True)
        check_number("RefineOptions.given_pose_std", self.given_pose_std, low=0, low_open=True)

    @classmethod
    def quick(cls, **overrides) -> RefineOptions:
        """The refinement of quick mode (``--quick``), where there is no cross-check's SIFT to reuse.

        It extracts SIFT itself, lighter than COLMAP's default: no 2x upsampled first octave (unless
        the image's long side is under 500 px), images at most 1600 px, 4096 features. It matches fewer
        overlapping pairs (at most 4 well-overlapping ones chosen per image, instead of 12) and runs one
        round of the fine pass (instead of up to 5). On the 48-frame 640 x 480 demo scene it takes about
        a third of the time COLMAP alone takes on the same images (2.8-3.0x faster), as accurate
        (docs/pipeline.md, "Quick mode").
        ``overrides`` replace fields of the preset.
        """
        preset = {"sift": QUICK_SIFT, "overlap": QUICK_OVERLAP, "bundle": QUICK_BUNDLE}
        return cls(**{**preset, **overrides})


@dataclass(frozen=True)
class RefineResult:
    """Refined cameras in the prediction's world frame (same scale and origin, up to the fit)."""

    status: RefineStatus
    names: tuple[str, ...]
    cam_from_world: np.ndarray  # [N, 3, 4] float64; flagged frames keep their feed-forward pose
    registered: np.ndarray  # [N] bool, True where refined
    cameras: tuple[PinholeCamera, ...]  # refined intrinsics (feed-forward ones where not refined)
    # Per frame OpenCV (k1, k2, p1, p2) of the refined lens (zeros where not refined); None: no distortion kept.
    distortion: tuple[tuple[float, float, float, float], ...] | None
    flagged: tuple[WeakFrame, ...]
    points_xyz: np.ndarray  # [M, 3] float64, prediction's world frame
    points_rgb: np.ndarray  # [M, 3] uint8
    num_pairs: int  # image pairs matched
    features: FeatureStats
    guidance: GuidanceStats | None  # None without feed-forward guidance of the matching
    screened: tuple[Suspect, ...]  # frames whose verified pairs put them far from the model's rotation
    dense: DenseStats | None  # None: no frame was short of SIFT matches (or dense evidence is off)
    relocalized: tuple[Relocalized, ...]  # frames placed again from their neighbours' renderings
    bundle: BundleSummary | None
    mean_reprojection_error_px: float
    ff_from_refined: Sim3 = field(repr=False)
    timings: Timings
    model_path: Path | None  # out_dir/refine/model: the refined frames and points (sparse/0 adds the others)
    database_path: Path | None  # the refinement's COLMAP database (SIFT and dense matches), out_dir/refine
    observations: np.ndarray | None  # [N] int, triangulated observations per frame in the refined model
    reconstruction: pycolmap.Reconstruction | None = field(default=None, repr=False, compare=False)

    def to_report(self) -> dict:
        err = self.mean_reprojection_error_px
        return {
            "status": self.status.value,
            "num_images": len(self.names),
            "num_refined": int(self.registered.sum()),
            "flagged": [
                {
                    "name": w.name,
                    "reason": w.reason.value,
                    "value": w.value,
                    "threshold": w.threshold,
                    "message": w.describe(),
                }
                for w in self.flagged
            ],
            "num_points": int(len(self.points_xyz)),
            "num_pairs_matched": self.num_pairs,
            "mean_reprojection_error_px": float(err) if np.isfinite(err) else None,
            "lens_k1": None if self.distortion is None else _median_k1(self.distortion, self.registered),
            "match_guidance": None if self.guidance is None else self.guidance.to_report(),
            "screened": [s.to_report(self.names) for s in self.screened],
            "dense_evidence": None if self.dense is None else self.dense.to_report(),
            "relocalized": [r.to_report(self.names) for r in self.relocalized],
            "bundle_adjustment": None if self.bundle is None else self.bundle.to_report(),
            "sim3_ff_from_refined_scale": self.ff_from_refined.scale,
            "model_path": None if self.model_path is None else str(self.model_path),
            "timings_s": self.timings.to_report(),
            "cpu_s": self.timings.cpu_report(),
            "features": self.features.to_report(),
        }


def _median_k1(distortion: tuple[tuple[float, ...], ...], registered: np.ndarray) -> float:
    return float(np.median([d[0] for d, r in zip(distortion, registered) if r]))


def _check_inputs(image_dir: Path, prediction: Prediction) -> None:
    missing = [n for n in prediction.names if not (Path(image_dir) / n).is_file()]
    if missing:
        raise InputError(
            f"{len(missing)} images of the prediction are not in {image_dir}, e.g. {missing[0]}",
            "pass the folder the model read",
        )
    if len(prediction) < 2:
        raise InputError(f"refinement needs at least two images, got {len(prediction)}", "add images")
    validate_prediction(prediction, allow_empty_depth=True)


def _shared_camera(prediction: Prediction) -> PinholeCamera | None:
    """Median intrinsics if every frame has the same image size, else None."""
    sizes = {(c.width, c.height) for c in prediction.cameras}
    if len(sizes) != 1:
        return None
    w, h = sizes.pop()
    k = np.median([[c.fx, c.fy, c.cx, c.cy] for c in prediction.cameras], axis=0)
    return PinholeCamera(w, h, float(k[0]), float(k[1]), float(k[2]), float(k[3]))


def _weak_by_features(stats: FeatureStats, options: RefineOptions) -> list[WeakFrame]:
    out = []
    for name, kps, matches in zip(stats.names, stats.num_keypoints, stats.num_inlier_matches):
        if kps < options.min_features:
            out.append(WeakFrame(name, WeakReason.FEW_FEATURES, int(kps), options.min_features))
        elif matches < options.min_matches:
            out.append(WeakFrame(name, WeakReason.FEW_MATCHES, int(matches), options.min_matches))
    return out


def _colmap_camera(camera: PinholeCamera, camera_id: int, square_pixels: bool) -> pycolmap.Camera:
    """PINHOLE, or SIMPLE_RADIAL (one focal length, radial term starting at 0) when pixels are square.

    With fx and fy both free, an orbit of cameras looking at a common point leaves the focal lengths
    and a common tilt of all cameras nearly undetermined; one focal length removes that freedom. The
    radial term is refined only in the fine pass (:class:`~ffrecon.sfm.bundle.BundleOptions`).
    """
    if not square_pixels:
        return pinhole_to_colmap(camera, camera_id)
    focal = float(np.sqrt(camera.fx * camera.fy))
    return pycolmap.Camera(
        model="SIMPLE_RADIAL",
        width=camera.width,
        height=camera.height,
        params=[focal, camera.cx, camera.cy, 0.0],
        camera_id=camera_id,
    )


def _prepare_database(
    image_dir: Path,
    prediction: Prediction,
    options: RefineOptions,
    db_path: Path,
    timer: StageTimer,
    mask_dir: Path | None = None,
) -> tuple[dict[str, int], list[PinholeCamera], dict[str, pycolmap.Camera], list[str]]:
    """Database with the feed-forward cameras and SIFT of every image.

    Returns the database image id of each name, the feed-forward camera used for each frame, the
    COLMAP camera of each name (as written to the database) and the names whose SIFT was reused.
    """
    names = prediction.names
    shared = _shared_camera(prediction) if options.single_camera else None
    cameras = [shared] * len(names) if shared is not None else list(prediction.cameras)
    image_ids = create_database(
        db_path,
        image_dir,
        names,
        camera_model=CameraModel.PINHOLE,
        single_camera=shared is not None,
        focal_prior_px=[c.fx for c in cameras],
    )
    db = pycolmap.Database.open(str(db_path))
    camera_of = {image.name: image.camera_id for image in db.read_all_images()}
    db.close()
    colmap_cameras = {
        camera_of[n]: _colmap_camera(c, camera_of[n], options.square_pixels) for n, c in zip(names, cameras)
    }
    set_database_cameras(db_path, list(colmap_cameras.values()))
    with timer.stage("feature_extraction"):
        copied = copy_features(options.reuse_features_from, db_path, names) if options.reuse_features_from else []
        if len(copied) < len(names):
            extract_sift(db_path, image_dir, [n for n in names if n not in copied], options.sift, mask_dir=mask_dir)
    if copied:
        logger.info("reused SIFT features of %d images from %s", len(copied), options.reuse_features_from)
    return image_ids, cameras, {n: colmap_cameras[camera_of[n]] for n in names}, copied


def _initial_model(
    prediction: Prediction,
    image_ids: dict[str, int],
    cameras: list[PinholeCamera],
    colmap_cameras: dict[str, pycolmap.Camera],
    shared: bool,
) -> pycolmap.Reconstruction:
    """The feed-forward cameras as a model whose image and camera ids equal the database's."""
    names = prediction.names
    order = sorted(range(len(names)), key=lambda k: image_ids[names[k]])
    rec = reconstruction_from_cameras(
        [names[k] for k in order],
        prediction.cam_from_world[order],
        [cameras[k] for k in order],
        share_identical_cameras=shared,
    )
    for image in rec.images.values():
        camera = colmap_cameras[image.name]
        if image_ids[image.name] != image.image_id or camera.camera_id != image.camera_id:
            raise RuntimeError(f"model and database disagree on the ids of {image.name}")
        rec.cameras[image.camera_id] = camera
    return rec


def _reuse_matches(
    db_path: Path, graph: OverlapGraph, names: tuple[str, ...], copied: list[str], options: RefineOptions
) -> list[tuple[str, str]]:
    """The cross-check's verified matches of the pairs that the feed-forward geometry says overlap at all.

    They cost nothing to reuse, so every such pair is taken, not only the best few per image that
    :func:`overlap_graph` picks for fresh matching: the refinement sees as many constraints as COLMAP did.
    """
    if options.reuse_features_from is None or not copied:
        return []
    reused_images = set(copied)
    score = graph.score()
    overlapping = [
        (names[i], names[j])
        for i in range(len(names))
        for j in range(i + 1, len(names))
        if score[i, j] >= options.overlap.min_any_overlap and {names[i], names[j]} <= reused_images
    ]
    reused = copy_verified_matches(options.reuse_features_from, db_path, overlapping)
    logger.info("reused the cross-check's verified matches of %d overlapping pairs", len(reused))
    return reused


def _match_unguided(
    db_path: Path, pairs: list[tuple[str, str]], reused: list[tuple[str, str]], options: RefineOptions, pairs_path: Path
) -> list[tuple[str, str]]:
    """COLMAP's matching and verification of ``pairs`` not among ``reused`` (verified already); none when
    the matching is to be guided from the start. Returns the pairs verified."""
    if options.guidance.mode is MatchGuidance.GUIDED:
        return []
    done = {frozenset(p) for p in reused}
    fresh = [p for p in pairs if frozenset(p) not in done]
    if fresh:
        match_pairs(db_path, fresh, options.sift, pairs_path)
    return list(reused) + fresh


def _guide(
    db_path: Path,
    prediction: Prediction,
    pairs: list[tuple[str, str]],
    verified: list[tuple[str, str]],
    options: RefineOptions,
    pairs_path: Path,
) -> GuidanceStats | None:
    """Check the ``verified`` matches against the prediction, or match ``pairs`` again guided by it, as
    ``options.guidance.mode`` says."""
    mode = options.guidance.mode
    if mode is MatchGuidance.NONE:
        return None
    if mode is not MatchGuidance.GUIDED:
        least = options.sift.min_num_inliers
        stats = filter_matches(db_path, prediction, verified, options.guidance, min_inliers=least)
        if mode is MatchGuidance.FILTER or stats.rejected_share <= options.guidance.auto_max_rejected:
            return stats
        logger.warning(
            "the feed-forward geometry rejects %.0f%% of the verified SIFT matches: look-alike surfaces (repeated "
            "texture?); matching again, guided by the feed-forward geometry",
            100 * stats.rejected_share,
        )
    stats = guided_matches(db_path, prediction, pairs, options.guidance)
    verify_pairs(db_path, write_pairs(pairs_path, pairs), options.sift)
    dropped = drop_contradicting_pairs(db_path, prediction, options.guidance.max_pair_gap_deg, options.screen)
    if dropped:
        logger.warning(
            "look-alike surfaces: %d verified pair(s) turned more than %.0f deg from the model's cameras dropped "
            "(a pattern's period off?): %s",
            len(dropped),
            options.guidance.max_pair_gap_deg,
            ", ".join(f"{prediction.names[g.index1]}-{prediction.names[g.index2]} ({g.gap_deg:.1f})" for g in dropped),
        )
    return dataclasses.replace(stats, dropped_pairs=len(dropped))


def _on_lookalikes(options: RefineOptions, guidance: GuidanceStats | None) -> RefineOptions:
    """The options for the adjustment once the matching is known. On look-alike surfaces (the matching was
    guided):

    - no frame is relocalised. Its renderings are matched by SIFT alone, and a pattern's period off is a pose the
      dense evidence then agrees with: on the repeated-texture room (seed 101, ``--quick``) a frame the model had
      within 3 deg was placed 84 deg off and called corrected;
    - two-view tracks are triangulated and the fine pass is robust (Cauchy), as with dense evidence. Ignoring them
      (COLMAP's default) leaves the few tracks over three frames, where a pair a period off joins the others'
      points wrongly: on the repeated-tile room of seed 204 (``tools/sweep_families.py``, ``--quick``) 459 points
      were left, and frames 0 and 1 ended 4-5 deg off with every one of their own matches right; with the
      two-view tracks, 0.04-0.22 deg.
    """
    if guidance is None or not guidance.lookalike:
        return options
    bundle = options.bundle
    if options.guidance.two_view_tracks:
        bundle = dataclasses.replace(bundle, ignore_two_view_tracks=False, robust_fine=True)
    if not options.relocalize.enabled:
        return dataclasses.replace(options, bundle=bundle)
    logger.info("look-alike surfaces: no frame is relocalised from renderings (a pattern's period would place it)")
    relocalize = dataclasses.replace(options.relocalize, enabled=False)
    return dataclasses.replace(options, bundle=bundle, relocalize=relocalize)


def _screen(db_path: Path, prediction: Prediction, verified: list, options: RefineOptions) -> tuple[Suspect, ...]:
    """The frames whose COLMAP-verified pairs (before any filtering by the model) contradict their model
    rotation; nothing to screen when the matching is guided from the start."""
    if not verified:
        return ()
    suspects, _ = screen_rotations(db_path, prediction, options.screen)
    for s in suspects:
        logger.warning(
            "%s: %d of its %d verified pairs put it %.1f deg from the model's rotation; starting the "
            "adjustment from their rotation",
            prediction.names[s.index],
            s.num_agreeing,
            s.num_pairs,
            s.gap_deg,
        )
    return suspects


def extract_refine_features(
    capture: Capture, sift: SiftOptions, out_dir: Path, threads: Callable[[], int] | None = None
) -> Path:
    """SIFT of the capture's photos (and masks) into a fresh COLMAP database, ``out_dir/sift/database.db``, for the
    refinement to reuse (:attr:`RefineOptions.reuse_features_from`); returns its path. ``threads``: see
    :func:`extract_sift`.

    Quick mode runs it beside the feed-forward inference, the part COLMAP's extraction plays in the full
    run: the features depend only on the photos, so they need not wait for the cameras.
    """
    db_path = Path(out_dir) / "sift" / "database.db"
    db_path.parent.mkdir(parents=True, exist_ok=True)
    image_dir, names = capture.image_dir, list(capture.names)
    create_database(db_path, image_dir, names, camera_model=CameraModel.PINHOLE, single_camera=False)
    extract_sift(db_path, image_dir, names, sift, threads=threads, mask_dir=capture.mask_dir)
    return db_path


def run_refine(
    image_dir: Path,
    prediction: Prediction,
    options: RefineOptions,
    out_dir: Path,
    mask_dir: Path | None = None,
    fixed: frozenset[str] = frozenset(),
    graph: OverlapGraph | None = None,
) -> RefineResult:
    """Refine the feed-forward cameras; writes the refined model to ``out_dir/refine/model`` (work files beside it;
    the run's ``sparse/0``, the final cameras, is written from it by the pipeline).

    Args:
        image_dir: folder holding the images named in ``prediction.names``.
        mask_dir: COLMAP's masks of those images (``<name>.png``, 0: no features there); None: none.
        fixed: frames whose poses (the user's, ``--poses``) stay as the prediction holds them: never reseeded,
            relocalised or registered again, constant in every adjustment.
        prediction: feed-forward cameras (cam_from_world, OpenCV) and depth, original-photo pixels.
        graph: the prediction's overlap graph when already made under ``options.overlap`` (the cross-check's
            model pairing: 28 s at 500 frames); None: made here.
    Returns:
        :class:`RefineResult` with poses in the prediction's world frame. Weak frames are flagged, not
        fatal; with fewer than two usable frames the status is FAILED and the feed-forward cameras
        are returned unrefined (nothing is written).
    """
    image_dir, out_dir = Path(image_dir), Path(out_dir)
    _check_inputs(image_dir, prediction)
    names = tuple(prediction.names)
    timer = StageTimer()
    work = out_dir / "refine"
    db_path = work / "database.db"
    pycolmap.set_random_seed(options.seed)
    with timer.stage("pair_selection"):
        if graph is None or graph.options != options.overlap or len(graph.overlap) != len(prediction):
            graph = overlap_graph(prediction, options.overlap)
    image_ids, cameras, colmap_cameras, copied = _prepare_database(
        image_dir, prediction, options, db_path, timer, mask_dir
    )
    pairs = [(names[i], names[j]) for i, j in graph.pairs]
    with timer.stage("matching"):
        reused = _reuse_matches(db_path, graph, names, copied, options)
        verified = _match_unguided(db_path, pairs, reused, options, work / "pairs.txt")
    with timer.stage("screening"):
        screened = tuple(s for s in _screen(db_path, prediction, verified, options) if names[s.index] not in fixed)
        start = reseeded(prediction, screened)
    with timer.stage("matching"):
        guidance = _guide(db_path, start, pairs, verified, options, work / "pairs.txt")
    options = _on_lookalikes(options, guidance)
    stats = feature_stats(db_path, names)
    flagged, rec, summary, dense, relocalized, stats = _adjust_with_dense(
        image_dir, start, graph, image_ids, (cameras, colmap_cameras), db_path, stats, options, timer, fixed
    )
    refined_names = {img.name for img in rec.images.values() if img.has_pose} if summary is not None else set()
    provenance = dict(
        database_path=db_path,
        flagged=tuple(flagged),
        num_pairs=len({frozenset(p) for p in pairs + reused}),
        features=stats,
        guidance=guidance,
        screened=screened,
        dense=dense,
        relocalized=relocalized,
        bundle=summary,
    )
    if len(refined_names) < 2:
        logger.warning("refinement failed: %d usable frames; keeping the feed-forward cameras", len(refined_names))
        return _unrefined_result(prediction, timings=timer.freeze(), **provenance)
    model_dir = out_dir / "refine" / "model"
    with timer.stage("export"):
        ff_from_refined = _export_in_ff_frame(rec, prediction, image_dir, model_dir)
    result = _refined_result(rec, prediction, ff_from_refined, model_dir, timings=timer.freeze(), **provenance)
    _log_refined(result)
    return result


def _log_refined(result: RefineResult) -> None:
    logger.info(
        "refined %d/%d frames, %d points, %.2f px reprojection error (%.1f s)",
        int(result.registered.sum()),
        len(result.names),
        len(result.points_xyz),
        result.mean_reprojection_error_px,
        result.timings.total_s,
    )


def _adjust_with_dense(image_dir, prediction, graph, image_ids, camera_sets, db_path, stats, options, timer, fixed):
    """Bundle adjustment with dense evidence: first for the frames SIFT leaves short of matches; then,
    once, for the frames the adjustment still left out (too few observations): those placed again
    from their neighbours' renderings get dense evidence from that pose, the others (not short the
    first time) from the model's, and a second adjustment starts from those poses. A capture SIFT
    handles well runs neither. Returns ``(flagged, rec, summary, dense, relocalized, stats)``."""
    names = tuple(prediction.names)
    cameras, colmap_cameras = camera_sets
    dense = None
    short = short_frames(names, stats.num_inlier_matches, options.dense) if options.dense.enabled else []
    if short:
        with timer.stage("dense_evidence"):
            dense = add_dense_evidence(db_path, image_dir, prediction, short, graph.reach(), options.dense)
        stats = feature_stats(db_path, names)
    flagged, rec, summary = _adjust(
        prediction, image_ids, cameras, colmap_cameras, db_path, stats, dense, options, timer, fixed
    )
    if not (options.dense.enabled and flagged):
        return flagged, rec, summary, dense, (), stats
    with timer.stage("dense_evidence"):
        left = [w for w in flagged if w.name not in fixed]  # given poses are not placed again
        start, more, found = _second_chance(image_dir, prediction, graph, rec, db_path, left, short, options)
    if more is None:
        return flagged, rec, summary, dense, found, stats
    dense = more if dense is None else dense.merged(more)
    stats = feature_stats(db_path, names)
    flagged, rec, summary = _adjust(
        start, image_ids, cameras, colmap_cameras, db_path, stats, dense, options, timer, fixed
    )
    return flagged, rec, summary, dense, found, stats


def _second_chance(image_dir, prediction, graph, rec, db_path, flagged, short, options: RefineOptions):
    """Dense evidence for the frames the first adjustment left out: ``(prediction to start the second
    adjustment from, DenseStats or None when nothing was added, relocalised frames)``."""
    names = tuple(prediction.names)
    left = [names.index(w.name) for w in flagged]
    placed = _model_poses_kept(rec, prediction, options.relocalize.max_source_change_deg)
    found = tuple(relocalize(image_dir, prediction, left, placed, options.relocalize))
    moved = {r.index for r in found}
    retry = [k for k in left if k not in set(short) and k not in moved]
    passes = []
    if retry:
        passes.append(add_dense_evidence(db_path, image_dir, prediction, retry, graph.reach(), options.dense))
    start = with_poses(prediction, found)
    if found:
        reach = reach_matrix(len(names), found)
        passes.append(add_dense_evidence(db_path, image_dir, start, sorted(moved), reach, options.dense))
    if not passes:
        return start, None, found
    more = passes[0] if len(passes) == 1 else passes[0].merged(passes[1])
    return start, more, found


def _model_poses_kept(rec: pycolmap.Reconstruction, prediction: Prediction, max_change_deg: float) -> list[int]:
    """Indices of the frames the adjustment registered within ``max_change_deg`` of the model's rotation
    (after the best common world rotation): their model pose and depth can be rendered from. A frame
    registered again far from its model pose (a correction) would render the model's error."""
    names = tuple(prediction.names)
    index = sorted(names.index(im.name) for im in rec.images.values() if im.has_pose)
    if len(index) < 2:
        return []
    by_name = {im.name: im for im in rec.images.values()}
    refined = np.stack([by_name[names[k]].cam_from_world().matrix()[:, :3] for k in index])
    change = aligned_rotation_errors_deg(refined, prediction.cam_from_world[index, :, :3])
    return [k for k, c in zip(index, change) if c <= max_change_deg]


def _adjust(
    prediction, image_ids, cameras, colmap_cameras, db_path, stats, dense, options: RefineOptions, timer, fixed=()
):
    """Triangulate and bundle-adjust the feed-forward cameras on the database's matches: ``(flagged, rec, summary)``
    (summary None when fewer than two frames were usable)."""
    flagged = _weak_by_features(stats, options)
    shared = len({c.camera_id for c in colmap_cameras.values()}) == 1
    rec = _initial_model(prediction, image_ids, cameras, colmap_cameras, shared)
    usable = set(prediction.names) - {w.name for w in flagged}
    summary = None
    # Two-view tracks count where they are all there is: dense evidence added, or a pair of photos (every
    # track of two frames is a two-view one; the Middlebury pair triangulated nothing without this).
    pairwise = dense is not None or len(usable) < 3
    bundle = dataclasses.replace(options.bundle, ignore_two_view_tracks=False) if pairwise else options.bundle
    bundle = dataclasses.replace(bundle, robust_fine=True) if dense is not None else bundle
    with timer.stage("triangulation_and_bundle_adjustment"), colmap_log_level():
        if len(usable) >= 2:
            obs = options.min_observations
            rec, summary, weak = refine_tracks(rec, db_path, usable, bundle, min_observations=obs, fixed=fixed)
            flagged += [WeakFrame(n, WeakReason.FEW_OBSERVATIONS, k, options.min_observations) for n, k in weak]
            # Links are checked where dense evidence made the model a chain of two-view links; given poses are the truth
            flagged += _detach(rec, prediction, options.links) if dense is not None and not fixed else []
    return flagged, rec, summary


def _detach(rec: pycolmap.Reconstruction, prediction: Prediction, options: LinkOptions) -> list[WeakFrame]:
    """Deregister the frames outside the largest group of trusted links (:func:`detached_frames`)."""
    detached = detached_frames(rec, prediction.names, prediction.cam_from_world, options)
    for name, _ in detached:
        rec.deregister_frame(rec.find_image_with_name(name).frame_id)
    if detached:
        names = [n for n, _ in detached]
        logger.warning("frames held by weak links or links the model contradicts, left out: %s", names)
    return [WeakFrame(n, WeakReason.WEAK_LINK, k, options.min_shared_points) for n, k in detached]


def _export_in_ff_frame(rec: pycolmap.Reconstruction, prediction: Prediction, image_dir: Path, model_dir: Path) -> Sim3:
    """Move ``rec`` into the prediction's world frame, colour its points and write it to ``model_dir``.

    Returns ``ff_from_refined``, the similarity that moved it.
    """
    ff_from_refined = sim3_to_ff_frame(rec, prediction.names, prediction.cam_from_world)
    with colmap_log_level():
        rec.extract_colors_for_all_images(str(image_dir))
    shutil.rmtree(model_dir, ignore_errors=True)
    write_reconstruction(rec, model_dir)
    return ff_from_refined


def _unrefined_result(prediction: Prediction, **provenance) -> RefineResult:
    """The FAILED result: the feed-forward cameras, unrefined, and no points or model."""
    n = len(prediction.names)
    return RefineResult(
        status=RefineStatus.FAILED,
        names=tuple(prediction.names),
        cam_from_world=prediction.cam_from_world.copy(),
        registered=np.zeros(n, bool),
        cameras=tuple(prediction.cameras),
        distortion=None,
        points_xyz=np.zeros((0, 3)),
        points_rgb=np.zeros((0, 3), np.uint8),
        mean_reprojection_error_px=float("nan"),
        ff_from_refined=Sim3.identity(),
        model_path=None,
        observations=None,
        reconstruction=None,
        **provenance,
    )


def _refined_result(
    rec: pycolmap.Reconstruction, prediction: Prediction, ff_from_refined: Sim3, model_dir: Path, **provenance
) -> RefineResult:
    """The refined model ``rec`` (already in the prediction's world frame) read back by image name.

    Frames that ``rec`` does not hold keep their feed-forward pose and camera.
    """
    names = tuple(prediction.names)
    cam_from_world, registered = cam_from_world_by_name(rec, names)
    cam_from_world[~registered] = prediction.cam_from_world[~registered]
    refined_cams = tuple(c if r else p for c, r, p in zip(cameras_by_name(rec, names), registered, prediction.cameras))
    by_name = {image.name: image for image in rec.images.values() if image.has_pose}
    coefficients = tuple(
        opencv_coefficients(rec.cameras[by_name[n].camera_id]) if n in by_name else NO_DISTORTION for n in names
    )
    points = rec.points3D
    xyz = np.array([p.xyz for p in points.values()], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in points.values()], dtype=np.uint8).reshape(-1, 3)
    rec.update_point_3d_errors()
    for weak in provenance["flagged"]:
        logger.warning("weak frame %s", weak.describe())
    return RefineResult(
        status=RefineStatus.SUCCESS if registered.all() else RefineStatus.PARTIAL,
        names=names,
        cam_from_world=cam_from_world,
        registered=registered,
        cameras=refined_cams,
        distortion=coefficients if any(c != NO_DISTORTION for c in coefficients) else None,
        points_xyz=xyz,
        points_rgb=rgb,
        mean_reprojection_error_px=float(rec.compute_mean_reprojection_error()),
        ff_from_refined=ff_from_refined,
        model_path=model_dir,
        observations=np.array([by_name[n].num_points3D if n in by_name else 0 for n in names], int),
        reconstruction=rec,
        **provenance,
    )


def sift_beside_skip_reason(
    mode: RunMode, concurrent: bool, model: Path | None, options: RefineOptions, views: int
) -> str | None:
    """Why the refinement's SIFT is not extracted ahead, beside the inference (only quick mode runs it there,
    when ``concurrent``, and when the refinement will run on a model's cameras and extracts its own), or None."""
    wanted = options.enabled and options.reuse_features_from is None and model is not None and views >= 2
    if mode is RunMode.QUICK and concurrent and wanted:
        return None
    return "extracted by the refinement itself (only quick mode extracts it beside the inference)"


def refine_skip_reason(prediction: Prediction | None) -> str | None:
    """Why the refinement does not run for want of a model's cameras, or None."""
    return "needs a model's cameras to refine; COLMAP's are final" if prediction is None else None


def run_refine_reusing(
    capture: Capture,
    prediction: Prediction,
    colmap: ColmapResult | Skipped,
    sift: Path | Skipped,
    options: RefineOptions,
    out_dir: Path,
) -> RefineResult:
    """:func:`run_refine` on a capture's photos (and masks), reusing SIFT already extracted (unless ``options``
    name features to reuse): the COLMAP cross-check's database (SIFT once, used twice), else quick mode's
    ``sift`` extracted beside the inference, else none (the refinement extracts its own). Intrinsics the user
    gave to hold fixed (``--intrinsics``; the prediction holds them) the adjustment keeps as they are
    (pinhole, focal fixed)."""
    fixed_intrinsics = bool(capture.known_cameras) and capture.intrinsics_fixed
    given = frozenset(n for n, p in zip(capture.names, capture.known_poses) if p is not None)
    if given and not capture.poses_fixed:  # the prediction holds the given poses: priors keep the centres near
        bundle = dataclasses.replace(options.bundle, use_pose_priors=True, prior_position_std=options.given_pose_std)
        options = dataclasses.replace(options, bundle=bundle)
    if fixed_intrinsics:
        bundle = dataclasses.replace(options.bundle, refine_focal_length=False, refine_principal_point=False)
        options = dataclasses.replace(options, bundle=bundle, square_pixels=False)
    if options.reuse_features_from is None and isinstance(colmap, ColmapResult):
        options = dataclasses.replace(options, reuse_features_from=colmap.database_path)
    elif options.reuse_features_from is None and isinstance(sift, Path):
        options = dataclasses.replace(options, reuse_features_from=sift)
    fixed = given if capture.poses_fixed else frozenset()
    graph = colmap.model_overlap if isinstance(colmap, ColmapResult) else None  # the same prediction's
    return run_refine(capture.image_dir, prediction, options, out_dir, capture.mask_dir, fixed, graph)
