"""The final cameras: which cameras a run keeps, per frame, and ``sparse/0``, the COLMAP model of them.

The refined cameras when the refinement kept two frames or more (frames it left out but COLMAP registered
take COLMAP's pose, moved into the refined frame); else the model's; else COLMAP's registered ones (also when
the evidence found the model unsuited). Frames the evidence contradicted stay out; those no independent
evidence confirmed are named (:attr:`FinalCameras.unconfirmed`), for the splat to refine photometrically.
The splat and the exports read these cameras and nothing else.

When the evidence checked none of the final cameras (every one unchecked: COLMAP and the refinement found
nothing to check them with), the run fails unless forced (:func:`require_checked`): missing evidence on one
camera is a warning, on every camera it means there is no result to trust.
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from ffrecon.colmap_io import add_posed_images, is_model_dir, pose_from_rigid, rigid_from_pose, write_reconstruction
from ffrecon.geometry.undistort import NO_DISTORTION, opencv_coefficients
from ffrecon.models.stage import FeedForwardResult
from ffrecon.sfm.crosscheck.gate_types import unchecked_verdict
from ffrecon.sfm.crosscheck.run import ColmapResult
from ffrecon.sfm.refine.options import RefineResult
from ffrecon.sfm.verify.verdicts import CameraStatus, EvidenceResult, FrameVerdict
from ffrecon.sfm.verify.witness import colmap_in_refined
from ffrecon.types import PinholeCamera, Skipped

log = logging.getLogger("ffrecon")


class CameraSource(enum.StrEnum):
    """Where the final cameras come from (also the labels of the pose comparisons)."""

    REFINED = "refined"  # the model's cameras refined by bundle adjustment
    FEEDFORWARD = "feed-forward"  # the model's cameras as it gave them
    COLMAP = "COLMAP"  # COLMAP's registered cameras (no model, or the model found unsuited)


@dataclass(frozen=True)
class FinalCameras:
    """The cameras the exports (and the splat) use: all frames, or COLMAP's registered ones."""

    indices: tuple[int, ...]  # into the capture's frames
    names: tuple[str, ...]
    cam_from_world: np.ndarray  # [M, 3, 4] float64, OpenCV
    cameras: tuple[PinholeCamera, ...]
    source: CameraSource
    # Per camera OpenCV (k1, k2, p1, p2) of the original photos (None: pinhole). The splat trains on
    # undistorted copies; transforms.json carries them (OPENCV) for the original images.
    distortion: tuple[tuple[float, float, float, float], ...] | None = None
    # Positions (into these lists) of the cameras no independent evidence confirmed: unchecked or corrected
    # (the splat may refine their poses photometrically). The model's cameras unrefined: all of them.
    unconfirmed: tuple[int, ...] = ()


def select_final_cameras(
    names: tuple[str, ...],
    ff: FeedForwardResult | Skipped,
    colmap: ColmapResult | Skipped,
    refine: RefineResult | Skipped,
    evidence: EvidenceResult | Skipped,
) -> FinalCameras | None:
    """Refined cameras when refinement kept two frames or more; else the model's (also when the evidence set the
    refined cameras aside); else COLMAP's registered ones (also when the model was found unsuited)."""
    every = tuple(range(len(names)))
    unsuited = isinstance(evidence, EvidenceResult) and evidence.model_unsuited
    set_aside = isinstance(evidence, EvidenceResult) and bool(evidence.refinement_set_aside)
    if not (unsuited or set_aside) and isinstance(refine, RefineResult) and refine.registered.sum() >= 2:
        model = ff.prediction.cam_from_world if isinstance(ff, FeedForwardResult) else None
        return _refined_final_cameras(names, colmap, refine, evidence, model)
    if not unsuited and isinstance(ff, FeedForwardResult):
        pred = ff.prediction
        # the frames the evidence left out stay out here too (a refinement set aside as a whole still judges each
        # frame at the model's camera: held-out street seed 269, frame 6 25 deg off, was exported though contradicted)
        per_image = evidence.per_image if isinstance(evidence, EvidenceResult) else ()
        kept = tuple(k for k in every if not per_image or per_image[k].status.kept)
        if len(kept) < len(every):
            log.info("frames left out, contradicted by the evidence: %s", [names[k] for k in every if k not in kept])
        cams = tuple(pred.cameras[k] for k in kept)
        poses = pred.cam_from_world[list(kept)]
        unconfirmed = tuple(range(len(kept)))
        kept_names = tuple(names[k] for k in kept)
        return FinalCameras(kept, kept_names, poses, cams, CameraSource.FEEDFORWARD, unconfirmed=unconfirmed)
    if isinstance(colmap, ColmapResult) and colmap.num_registered >= 2:
        kept = tuple(int(i) for i in np.flatnonzero(colmap.registered))
        kept_names = tuple(names[i] for i in kept)
        cameras = tuple(colmap.cameras[i] for i in kept)
        distortion = tuple(_colmap_lens(colmap, kept_names))
        poses = colmap.cam_from_world[list(kept)]
        return FinalCameras(kept, kept_names, poses, cameras, CameraSource.COLMAP, distortion)
    return None


def _refined_final_cameras(
    names: tuple[str, ...],
    colmap: ColmapResult | Skipped,
    refine: RefineResult,
    evidence: EvidenceResult | Skipped,
    model: np.ndarray | None = None,
) -> FinalCameras:
    """The refined cameras; frames the refinement left out but COLMAP registered (evidence: COLMAP only)
    take COLMAP's pose, moved into the refined frame by a Sim(3) fit over the frames both hold, and its lens.
    Frames the evidence kept at the model's camera (:attr:`CameraStatus.MODEL_FITS`) take ``model``'s pose
    (``[N, 3, 4]``, the model's cameras: the refined ones are in its world)."""
    poses, cameras = refine.cam_from_world.copy(), list(refine.cameras)
    distortion = list(refine.distortion or [NO_DISTORTION] * len(poses))
    per_image = evidence.per_image if isinstance(evidence, EvidenceResult) else ()
    colmap_only = [
        k
        for k, e in enumerate(per_image)
        if e.status in (CameraStatus.COLMAP_ONLY, CameraStatus.CORRECTED) and not refine.registered[k]
    ]
    if colmap_only:
        moved = colmap_in_refined(colmap, refine)
        lenses = _colmap_lens(colmap, [names[k] for k in colmap_only])
        for k, lens in zip(colmap_only, lenses):
            poses[k] = moved[k]
            cameras[k] = colmap.cameras[k]
            distortion[k] = lens
        log.info("%d frames not refined take COLMAP's poses: %s", len(colmap_only), [names[k] for k in colmap_only])
    at_model = [k for k, e in enumerate(per_image) if e.status is CameraStatus.MODEL_FITS and model is not None]
    poses[at_model] = model[at_model] if at_model else poses[at_model]
    kept = [k for k in range(len(poses)) if not per_image or per_image[k].status.kept]
    if len(kept) < len(poses):
        left_out = [names[k] for k in range(len(poses)) if k not in kept]
        log.info("frames left out, contradicted by the evidence: %s", left_out)
    lens = tuple(distortion[k] for k in kept) if any(d != NO_DISTORTION for d in distortion) else None
    kept_names = tuple(names[k] for k in kept)
    unconfirmed = tuple(
        p for p, k in enumerate(kept) if per_image and per_image[k].verdict is not FrameVerdict.CONFIRMED
    )
    cams = tuple(cameras[k] for k in kept)
    return FinalCameras(tuple(kept), kept_names, poses[kept], cams, CameraSource.REFINED, lens, unconfirmed=unconfirmed)


def _colmap_lens(colmap: ColmapResult, names: tuple[str, ...] | list[str]) -> list[tuple[float, float, float, float]]:
    """OpenCV (k1, k2, p1, p2) of COLMAP's camera of each of ``names`` (registered images)."""
    by_name = {im.name: im for im in colmap.reconstruction.images.values()}
    return [opencv_coefficients(colmap.reconstruction.cameras[by_name[n].camera_id]) for n in names]


def source_model(
    source: CameraSource,
    ff: FeedForwardResult | Skipped,
    colmap: ColmapResult | Skipped,
    refine: RefineResult | Skipped,
) -> Path | None:
    """The COLMAP model folder of the final cameras' source, None when it has none."""
    folders = {
        CameraSource.REFINED: refine.model_path if isinstance(refine, RefineResult) else None,
        CameraSource.COLMAP: colmap.model_path if isinstance(colmap, ColmapResult) else None,
        CameraSource.FEEDFORWARD: ff.sparse_dir if isinstance(ff, FeedForwardResult) else None,
    }
    return folders[source]


FINAL_MODELS = (Path("sparse") / "0", Path("colmap") / "sparse" / "0")  # relative to the run folder


def write_final_model(final: FinalCameras | None, folder: Path | None, work: Path) -> Path | None:
    """``work/sparse/0`` and ``work/colmap/sparse/0``: every final camera as a COLMAP model, where downstream
    tools look (docs/contracts.md, "Output folder"; ``colmap/sparse/0`` is where nerfstudio's COLMAP data
    parser looks by default). The model of the final cameras' source, ``folder`` (the refinement's, COLMAP's
    in a run without a model, the model's when the refinement failed or was turned off), plus, posed and
    without points, the final frames that model lacks (a frame the refinement left out keeps the model's
    camera, unchecked).

    Runs every time (a small model), so both are always the final cameras of this run; without them both are
    removed. The refinement's own model stays in ``refine/model``, which a resumed run reads. Returns
    ``work/sparse/0``, or None when there is none.
    """
    targets = [work / rel for rel in FINAL_MODELS]
    for stale in (targets[0], work / "colmap"):  # colmap/ holds nothing else (the cross-check is crosscheck/)
        shutil.rmtree(stale, ignore_errors=True)
    if final is None or folder is None or not is_model_dir(Path(folder)):
        return None
    rec = pycolmap.Reconstruction(str(folder))
    dropped = _drop_frames_not_final(rec, set(final.names))
    moved = _repose_frames(rec, final)
    added = add_posed_images(rec, final.names, final.cam_from_world, final.cameras, final.distortion)
    for target in targets:
        write_reconstruction(rec, target)
    log.info(
        "sparse/0 and colmap/sparse/0: the final cameras (%s, from %s)%s%s%s",
        final.source,
        folder,
        f", plus {len(added)} frame(s) it lacks, posed without points: {', '.join(added)}" if added else "",
        f", without {len(dropped)} frame(s) the evidence left out: {', '.join(dropped)}" if dropped else "",
        f", {len(moved)} frame(s) at the model's camera, without points: {', '.join(moved)}" if moved else "",
    )
    return targets[0]


def _repose_frames(rec: pycolmap.Reconstruction, final: FinalCameras, tol: float = 1e-6) -> list[str]:
    """Give each frame ``rec`` holds at another pose than its final camera (one the evidence kept at the model's
    camera, :attr:`CameraStatus.MODEL_FITS`) the final pose, without observations: its points were triangulated
    with the pose set aside. Returns their names."""
    moved = []
    for name, pose in zip(final.names, final.cam_from_world):
        image = rec.find_image_with_name(name)
        if image is None or not image.has_pose:
            continue
        if np.abs(pose_from_rigid(image.cam_from_world()) - pose).max() <= tol:
            continue
        frame_id = image.frame_id
        rec.deregister_frame(frame_id)
        rec.frame(frame_id).rig_from_world = rigid_from_pose(pose)
        rec.register_frame(frame_id)
        moved.append(name)
    return moved


def _drop_frames_not_final(rec: pycolmap.Reconstruction, final: set[str]) -> list[str]:
    """Deregister from ``rec`` the frames it holds that are not final cameras (one the refinement registered
    that the evidence then contradicted, e.g. on one planar pair): their observations go, points seen by
    fewer than two frames with them, and the written model no longer lists them. Returns their names."""
    dropped = sorted(im.name for im in rec.images.values() if im.has_pose and im.name not in final)
    for name in dropped:
        rec.deregister_frame(rec.find_image_with_name(name).frame_id)
    return dropped


def final_cameras(
    names: tuple[str, ...],
    ff: FeedForwardResult | Skipped,
    colmap: ColmapResult | Skipped,
    refine: RefineResult | Skipped,
    evidence: EvidenceResult | Skipped,
    work: Path,
) -> FinalCameras | None:
    """The final cameras (:func:`select_final_cameras`), written as ``work/sparse/0`` (:func:`write_final_model`)."""
    final = select_final_cameras(names, ff, colmap, refine, evidence)
    write_final_model(final, final and source_model(final.source, ff, colmap, refine), work)
    return final


def require_checked(evidence: EvidenceResult, colmap: ColmapResult | Skipped, refine: RefineResult) -> EvidenceResult:
    """``evidence`` with its ``checked_share`` verdict failing (blocking unless forced) when no final camera was
    checked: every frame kept is unchecked (none confirmed, none corrected, none refined on guided matches). Else
    ``evidence`` as it is."""
    kept = [e for e in evidence.per_image if e.status.kept]
    # a frame refined on guided matches (look-alike surfaces), in a part placed by the model or loosely held is
    # unchecked, but adjusted on matches that fit
    fitted = (CameraStatus.GUIDED, CameraStatus.PART, CameraStatus.LOOSE, CameraStatus.COLMAP_NEAR)
    held = any(e.verdict is not FrameVerdict.UNCHECKED or e.status in fitted for e in kept)
    if evidence.model_unsuited or evidence.refinement_set_aside or not kept or held:
        return evidence
    colmap_text = (
        f"COLMAP registered {colmap.num_registered} of {len(colmap.names)} images and "
        if isinstance(colmap, ColmapResult)
        else ""
    )
    refined = int(np.count_nonzero(refine.registered))
    tried = f"{colmap_text}the refinement confirmed none of the {len(kept)} frames ({refined} refined)"
    failed = unchecked_verdict(len(kept), tried)
    forced = "; continuing anyway (--force)" if evidence.gates.forced else ""
    log.warning("gate %s: %s - %s%s", failed.name, failed.status.value, failed.reason, forced)
    verdicts = [failed if v.name == failed.name else v for v in evidence.gates.verdicts]
    verdicts += [] if failed in verdicts else [failed]
    return dataclasses.replace(evidence, gates=dataclasses.replace(evidence.gates, verdicts=tuple(verdicts)))
