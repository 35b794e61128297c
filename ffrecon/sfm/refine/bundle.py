"""Triangulation and bundle adjustment of a model whose poses start at the feed-forward cameras.

Built on pycolmap's incremental-mapper pieces (the database cache's correspondence graph, its
triangulator and observation manager), with the bundle adjuster configured here so that the gauge,
intrinsics and pose priors are under ffrecon's control and the solver summary is kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

from ffrecon.checks import check_number
from ffrecon.sfm.refine.lens import LensTrial


@dataclass(frozen=True, kw_only=True)
class BundleOptions:
    coarse_error_deg: float = 5.0  # feed-forward pose error to tolerate in the first (coarse) pass
    max_reproj_error_px: float = 4.0  # COLMAP's filter threshold, used in the fine pass
    min_tri_angle_deg: float = 1.5
    # COLMAP's default: a point seen in two images only is not triangulated (more robust, fewer points).
    # The refinement allows them where dense evidence was added: its correspondences are mostly pairwise.
    ignore_two_view_tracks: bool = True
    # The fine pass's loss: squared (COLMAP's) or Cauchy at 1 px. The refinement makes it robust where dense
    # evidence was added: there a few correspondences 1.5-4 px off (under the filter) bend weakly held frames.
    robust_fine: bool = False
    refine_focal_length: bool = True
    refine_principal_point: bool = False
    # Run the fine pass also with the radial term of SIMPLE_RADIAL cameras free (never the coarse pass, where
    # it would soak up feed-forward pose errors); that model is kept only where it moves an image corner by at least
    # min_distortion_px AND lowers the mean reprojection error by at least min_distortion_gain. On a
    # forward walk, focal length and k trade off almost freely; an unsupported k only bends the poses.
    refine_distortion: bool = True
    min_distortion_px: float = 0.5
    min_distortion_gain: float = 0.10  # measured: 15% on a 6 px barrel lens, 8% spurious on look-alike texture
    use_pose_priors: bool = False  # keep camera centres near the feed-forward ones (position priors)
    prior_position_std: float = 0.02  # prior std as a fraction of the extent of feed-forward centres
    coarse_refinements: int = 1  # rounds of (bundle adjustment, track completion, filtering), coarse pass
    coarse_function_tolerance: float = 1e-5  # relative cost change that ends a coarse adjustment
    coarse_max_iterations: int = 10  # Ceres iterations per coarse adjustment: close enough to re-triangulate
    max_refinements: int = 5  # rounds in the fine pass
    fine_function_tolerance: float = 0.0  # relative cost change that ends a fine adjustment (0: run to convergence)
    # Stop when fewer observations than this fraction change. Measured on the looped 500-frame bench scene: the
    # fine pass's rounds changed 9.6 %, 1.0 %, 0.16 %, 0.06 %; stopping at 0.2 % instead of 0.1 % (and without
    # the adjustment after the last round) took the pass from 109 to 62 s, median rotation 0.0153 -> 0.0152 deg.
    max_refinement_change: float = 0.002
    max_num_iterations: int = 100  # Ceres iterations per bundle adjustment
    max_solver_seconds: float = 600.0  # wall-clock bound per bundle adjustment (Ceres stops and keeps its best)
    num_threads: int = 1  # 1 makes refinement repeatable (multi-threaded Ceres sums in varying order); -1: all
    # Long captures: from thin_from_images registered frames (0: never), each adjustment first solves with every
    # track thinned to at most max_track_images observations spread along it, then the whole problem (the
    # coarse pass stops at the thinned solve). On a dense video a point is seen by more frames the more frames
    # there are, so the cameras coupled through points, and the sparse solver's cost, grow as frames^2 or
    # worse; thinned tracks keep that coupling bounded. The whole problem then starts near its optimum and
    # runs to after_thin_function_tolerance with Ceres' iterative Schur solver, whose cost per step grows with
    # the observations alone. Measured on the looped 500-frame bench scene (refined model, cameras moved):
    # 27.6 s for the whole problem, 10.2 s thinned then whole, rotations within 0.011 deg of each other.
    thin_from_images: int = 200
    max_track_images: int = 8
    after_thin_function_tolerance: float = 1e-6

    def __post_init__(self) -> None:
        for name in ("coarse_error_deg", "max_reproj_error_px", "prior_position_std", "max_solver_seconds"):
            check_number(f"BundleOptions.{name}", getattr(self, name), low=0, low_open=True)
        for name in ("min_tri_angle_deg", "min_distortion_px", "coarse_function_tolerance", "fine_function_tolerance"):
            check_number(f"BundleOptions.{name}", getattr(self, name), low=0)
        for name in ("min_distortion_gain", "max_refinement_change"):
            check_number(f"BundleOptions.{name}", getattr(self, name), low=0, high=1)
        for name in ("coarse_refinements", "coarse_max_iterations", "max_refinements", "max_num_iterations"):
            check_number(f"BundleOptions.{name}", getattr(self, name), low=0, integer=True)
        check_number("BundleOptions.thin_from_images", self.thin_from_images, low=0, integer=True)
        check_number("BundleOptions.max_track_images", self.max_track_images, low=2, integer=True)
        check_number("BundleOptions.after_thin_function_tolerance", self.after_thin_function_tolerance, low=0)


@dataclass(frozen=True)
class BundleSummary:
    """The last bundle adjustment of the fine pass."""

    termination: str
    usable: bool
    num_residuals: int
    num_iterations: int
    initial_cost: float
    final_cost: float
    num_adjustments: int  # bundle adjustments over both passes
    thinned_observations: int = 0  # observations the last adjustment's thinned solve left out (0: not thinned)
    lens: LensTrial = LensTrial.NONE

    def to_report(self) -> dict:
        return {
            "termination": self.termination,
            "usable": self.usable,
            "num_residuals": self.num_residuals,
            "num_iterations": self.num_iterations,
            "initial_cost": self.initial_cost,
            "final_cost": self.final_cost,
            "num_adjustments": self.num_adjustments,
            "thinned_observations": self.thinned_observations,
            "lens": self.lens.value,
        }


def _summary(adjust: _Adjuster, lens: LensTrial = LensTrial.NONE) -> BundleSummary | None:
    """The last adjustment's summary (None: none ran)."""
    if adjust.last is None:
        return None
    solver_summary, count = adjust.last, adjust.count
    ceres = getattr(solver_summary, "ceres_summary", None)
    iterations = len(getattr(ceres, "iterations", [])) if ceres is not None else 0
    return BundleSummary(
        termination=str(solver_summary.termination_type.name),
        usable=bool(solver_summary.is_solution_usable()),
        num_residuals=int(solver_summary.num_residuals),
        num_iterations=int(getattr(ceres, "num_successful_steps", 0) + getattr(ceres, "num_unsuccessful_steps", 0))
        or iterations,
        initial_cost=float(getattr(ceres, "initial_cost", np.nan)),
        final_cost=float(getattr(ceres, "final_cost", np.nan)),
        num_adjustments=count,
        thinned_observations=adjust.thinned,
        lens=lens,
    )


def _pose_priors(
    rec: pycolmap.Reconstruction, prior_centers: dict[int, np.ndarray], std: float
) -> list[pycolmap.PosePrior]:
    priors = []
    for image_id, center in prior_centers.items():
        if not rec.exists_image(image_id) or not rec.image(image_id).has_pose:
            continue
        prior = pycolmap.PosePrior()
        prior.pose_prior_id = image_id
        prior.corr_data_id = rec.image(image_id).data_id
        prior.position = np.asarray(center, np.float64)
        prior.position_covariance = np.eye(3) * std**2
        prior.coordinate_system = pycolmap.PosePriorCoordinateSystem.CARTESIAN
        priors.append(prior)
    return priors


class _Adjuster:
    """One bundle-adjustment configuration, applied repeatedly to a changing model."""

    def __init__(
        self,
        options: BundleOptions,
        prior_centers: dict[int, np.ndarray] | None,
        prior_std: float,
        constant: frozenset[int] = frozenset(),
    ) -> None:
        self.options = options
        self.prior_centers = prior_centers
        self.prior_std = prior_std
        self.constant = constant  # image ids whose poses stay as they are (given poses, held fixed)
        self.count = 0
        self.last: pycolmap.BundleAdjustmentSummary | None = None
        self.refine_distortion = False  # switched on for the fine pass
        self.whole_after_thin = True  # switched off for the coarse pass: the thinned solve is close enough
        self.thinned = 0  # observations the last thinned solve left out

    def __call__(
        self,
        rec: pycolmap.Reconstruction,
        loss: pycolmap.LossFunctionType,
        *,
        function_tolerance: float = 0.0,
        max_iterations: int | None = None,
    ) -> bool:
        options = self.options
        iterative, self.thinned = False, 0
        if rec.num_reg_images() >= options.thin_from_images > 0:
            thin, self.thinned = _thinned(rec, options.max_track_images)
            # Followed by the whole problem, the thinned solve need not run to convergence: from the coarse
            # cameras it took 101 Ceres iterations (34.6 s of the 500-frame bench scene), to 1e-6 69 (22.0 s).
            after = options.after_thin_function_tolerance if self.whole_after_thin else 0.0
            thin_tolerance = max(function_tolerance, after)
            summary = self._solve(thin, loss, thin_tolerance, max_iterations, iterative=False)
            if summary is None:
                return False
            if summary.is_solution_usable():
                _copy_solution(thin, rec)
            if not self.whole_after_thin:
                return self._done(summary)
            function_tolerance = max(function_tolerance, after)
            iterative = True
        summary = self._solve(rec, loss, function_tolerance, max_iterations, iterative=iterative)
        return False if summary is None else self._done(summary)

    def _done(self, summary: pycolmap.BundleAdjustmentSummary) -> bool:
        self.last = summary
        self.count += 1
        return bool(summary.is_solution_usable())

    def _solve(
        self,
        rec: pycolmap.Reconstruction,
        loss: pycolmap.LossFunctionType,
        function_tolerance: float,
        max_iterations: int | None,
        *,
        iterative: bool,
    ) -> pycolmap.BundleAdjustmentSummary | None:
        """One Ceres solve of ``rec`` (None: nothing to adjust); ``iterative``: Ceres' iterative Schur solver."""
        ba = self._ba_options(loss, function_tolerance, max_iterations, iterative)
        config = pycolmap.BundleAdjustmentConfig()
        for image_id in rec.reg_image_ids():
            config.add_image(image_id)
        if config.num_residuals(rec) == 0:
            return None
        fixed = [i for i in rec.reg_image_ids() if i in self.constant]
        for image_id in fixed:
            config.set_constant_rig_from_world_pose(rec.image(image_id).frame_id)
        if len(fixed) >= 2:  # two fixed poses or more fix the gauge themselves
            adjuster = pycolmap.create_default_bundle_adjuster(ba, config, rec)
        elif self.prior_centers is not None:
            priors = _pose_priors(rec, self.prior_centers, self.prior_std)
            prior_options = pycolmap.PosePriorBundleAdjustmentOptions()
            prior_options.alignment_ransac.random_seed = 0
            adjuster = pycolmap.create_pose_prior_bundle_adjuster(ba, prior_options, config, priors, rec)
        else:
            config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
            adjuster = pycolmap.create_default_bundle_adjuster(ba, config, rec)
        return adjuster.solve()

    def _ba_options(
        self, loss: pycolmap.LossFunctionType, function_tolerance: float, max_iterations: int | None, iterative: bool
    ) -> pycolmap.BundleAdjustmentOptions:
        ba = pycolmap.BundleAdjustmentOptions()
        ba.refine_focal_length = self.options.refine_focal_length
        ba.refine_principal_point = self.options.refine_principal_point
        ba.refine_extra_params = self.refine_distortion
        ba.print_summary = False
        ba.ceres.loss_function_type = loss
        ba.ceres.loss_function_scale = 1.0  # pixels
        solver = ba.ceres.solver_options
        solver.num_threads = self.options.num_threads
        solver.max_num_iterations = max_iterations or self.options.max_num_iterations
        solver.function_tolerance = function_tolerance
        solver.max_solver_time_in_seconds = self.options.max_solver_seconds
        if iterative:  # pycolmap keeps Ceres' enums in a private module: reach them through the fields' types
            ba.ceres.auto_select_solver_type = False
            solver.linear_solver_type = type(solver.linear_solver_type).ITERATIVE_SCHUR
            solver.preconditioner_type = type(solver.preconditioner_type).SCHUR_JACOBI
        return ba


_GOLDEN = 0.6180339887  # spreads the kept observations' phase over the points


def _thinned(rec: pycolmap.Reconstruction, max_images: int) -> tuple[pycolmap.Reconstruction, int]:
    """A copy of ``rec`` whose tracks keep at most ``max_images`` observations, evenly spaced along the track's
    frames (in image-id order) from a phase that varies from point to point, so that every frame keeps a share
    of its points; and the number of observations left out. (COLMAP has no such option: written here.)"""
    thin = pycolmap.Reconstruction(rec)
    removed = 0
    for point_id in list(thin.point3D_ids()):
        elements = thin.point3D(point_id).track.elements
        n = len(elements)
        if n <= max_images:
            continue
        phase = (point_id * _GOLDEN) % 1.0
        keep = {int((k + phase) * n / max_images) for k in range(max_images)}
        for k, (image_id, point2D_idx) in enumerate(sorted((e.image_id, e.point2D_idx) for e in elements)):
            if k not in keep:
                thin.delete_observation(image_id, point2D_idx)
                removed += 1
    return thin, removed


def _diverged(rec: pycolmap.Reconstruction, max_error_px: float) -> str | None:
    """Why the refined model came back broken (None: it did not), after deleting the points the last adjustment
    left over ``max_error_px`` (non-finite ones included): the filter of each round runs before its adjustment,
    so a point can end a round broken.

    Broken: more than half its points are (the cameras scattered), or the rest's mean error is not finite. Seen on
    the repeated-tile street (held-out seed 201, ``--quick``, frame 6 25 deg off): Ceres once reported a linear
    solver failure and the cameras scattered at a mean of 5e152 px. Later on the same case the cameras ended
    within 1.5 deg (median 0.12 px) and one point of 2,569 at 1e154 px made the mean 5e152: a mean over the points
    cannot tell the two apart, so broken points are counted, not averaged.
    """
    rec.update_point_3d_errors()
    total = rec.num_points3D()
    broken = [point_id for point_id, point in rec.points3D.items() if not point.error <= max_error_px]
    for point_id in broken:
        rec.delete_point3D(point_id)
    error = rec.compute_mean_reprojection_error()
    if total and len(broken) > total / 2:
        return f"{len(broken)} of its {total} points over {max_error_px:g} px"
    return None if np.isfinite(error) else f"mean reprojection error {error}"


def _copy_solution(source: pycolmap.Reconstruction, target: pycolmap.Reconstruction) -> None:
    """The poses, intrinsics and point positions of ``source`` (a thinned copy of ``target``) into ``target``."""
    for frame_id in {target.image(i).frame_id for i in target.reg_image_ids()}:
        target.frame(frame_id).rig_from_world = source.frame(frame_id).rig_from_world
    for camera_id in target.cameras:
        target.camera(camera_id).params = source.camera(camera_id).params
    for point_id in source.point3D_ids():
        target.point3D(point_id).xyz = source.point3D(point_id).xyz


def _tri_options(angle_deg: float, reproj_px: float, options: BundleOptions) -> pycolmap.IncrementalTriangulatorOptions:
    tri = pycolmap.IncrementalTriangulatorOptions()
    tri.ignore_two_view_tracks = options.ignore_two_view_tracks
    tri.create_max_angle_error = max(angle_deg, tri.create_max_angle_error)
    tri.continue_max_angle_error = max(angle_deg, tri.continue_max_angle_error)
    tri.re_max_angle_error = max(angle_deg, tri.re_max_angle_error)
    tri.merge_max_reproj_error = max(reproj_px, tri.merge_max_reproj_error)
    tri.complete_max_reproj_error = max(reproj_px, tri.complete_max_reproj_error)
    tri.random_seed = 0
    return tri


def _mapper_options(filter_px: float, options: BundleOptions) -> pycolmap.IncrementalMapperOptions:
    mapper = pycolmap.IncrementalMapperOptions()
    mapper.filter_max_reproj_error = filter_px
    mapper.filter_min_tri_angle = options.min_tri_angle_deg
    mapper.num_threads = options.num_threads
    mapper.random_seed = 0
    mapper.abs_pose_refine_focal_length = False  # re-registered frames share the refined camera
    mapper.abs_pose_refine_extra_params = False
    return mapper
