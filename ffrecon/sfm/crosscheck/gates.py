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
import functools
import logging

import numpy as np
import pycolmap

from ffrecon.capture.quality import CaptureQuality
from ffrecon.sfm.crosscheck.gate_types import (
    _FIXES,
    UNCHECKED_FIX,
    FailureCause,
    GateOptions,
    GatesResult,
    GateStatus,
    GateVerdict,
    MaskedOut,
    unchecked_verdict,
)
from ffrecon.sfm.crosscheck.registration import registration_gate
from ffrecon.sfm.crosscheck.run import ColmapResult
from ffrecon.types import Prediction, Skipped

logger = logging.getLogger("ffrecon.sfm")
# A frame whose mask (--masks) keeps less than this share of its pixels counts as masked out: its photo gives
# no features and no depth, whatever it shows.
MIN_MASK_USE = 0.01


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
    :mod:`ffrecon.sfm.verify.evidence`): its registration and sparse-cloud verdicts are reported, not blocking.
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


def gate_before_refinement(
    prediction: Prediction | None, options: GateOptions, *, force: bool, masked_out: MaskedOut | None = None
) -> str | None:
    """Why a failed gate stops a run with a model before its cameras are refined, or None: with a model COLMAP
    is a witness (:func:`run_gates`), so only the gates that do not read COLMAP's model can stop it, the
    model's depth coverage; the refinement then need not wait for COLMAP's mapping. :func:`gate_poses` reports
    the same verdict, with COLMAP's."""
    verdict = depth_coverage_gate(prediction, options, masked_out=masked_out)
    return f"gate '{verdict.name}' failed: {verdict.reason}" if verdict.failed and not force else None


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
    witness: the final cameras are judged on their own evidence instead (:mod:`ffrecon.sfm.verify.evidence`).

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
