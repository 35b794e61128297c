"""When COLMAP's model is a witness: healthy (it passed its own gates), distrusted on look-alike surfaces, and
when it shows the model unsuited to the photos.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ffrecon.errors import NonFiniteError
from ffrecon.geometry.alignment import umeyama
from ffrecon.geometry.poses import camera_centers
from ffrecon.geometry.rotations import rotation_angle_deg
from ffrecon.sfm.compare.poses import compare_poses
from ffrecon.sfm.crosscheck.gate_types import GatesResult
from ffrecon.sfm.crosscheck.run import ColmapResult
from ffrecon.sfm.refine.options import RefineResult


def colmap_in_refined(colmap: ColmapResult, refine: RefineResult) -> np.ndarray:
    """COLMAP's cameras ``[N, 3, 4]`` moved into the refined cameras' world (the model's) by a Sim(3) fit of the
    centres of the frames both hold (meaningful where COLMAP registered the frame). Raises NonFiniteError (with a
    fix) when the fit fails."""
    both = refine.registered & colmap.registered
    try:
        sim = umeyama(camera_centers(colmap.cam_from_world[both]), camera_centers(refine.cam_from_world[both]))
    except NonFiniteError as err:
        raise err.with_fix("COLMAP's or the refinement's cameras are broken: run again with --fresh") from None
    return sim.transform_cam_from_world(colmap.cam_from_world)


def _healthy(colmap: ColmapResult | None, witness: GatesResult) -> bool:
    """Whether COLMAP's model passed its own gates (depth coverage is the model's, not COLMAP's)."""
    return colmap is not None and not any(v.failed for v in witness.verdicts if v.name != "depth_coverage")


def _lookalike(refine: RefineResult) -> bool:
    """Whether the refinement matched on look-alike surfaces (its matching was guided by the model)."""
    return refine.guidance is not None and refine.guidance.lookalike


def _distrusted(
    refine: RefineResult,
    colmap: ColmapResult | None,
    witness: GatesResult,
    options,
    ff_cam_from_world: np.ndarray | None = None,
) -> str:
    """Why COLMAP's model is no witness ("" when it is): on look-alike surfaces, it failed its own gates, or it
    disagrees with the refined cameras on most of the frames both hold; anywhere, it failed its own gates and
    disagrees with the refined cameras on most of the frames both hold.

    The refinement calls surfaces look-alike when the model's geometry rejects most of COLMAP's verified
    matches and guides the matching instead (:mod:`ffrecon.sfm.refine.guided`). COLMAP built its model on those
    matches: on the repeated-texture room (seed 101) it registered 4 of 8 frames 7-16 deg off the truth, and
    its disagreement left out four frames the refinement had placed within 0.2 deg. A model that passed its gates
    can be a period off too: on the repeated-tile street of held-out seed 215 COLMAP registered all 8 frames on 320
    points at 0.9 px, three of them 18-28 deg off; it disagreed with the model and the refinement on every frame,
    called the model unsuited, and its cameras (median 3.8 deg off, the model's 2.6) replaced them. There two
    reconstructions from the same ambiguous matches disagree and neither checks the other: COLMAP is no witness,
    and the refined frames stay unconfirmed ("refined on guided matches"). Where they agree on most frames, a
    healthy COLMAP model stays a witness.

    A model that failed its gates elsewhere is a witness of the frames it holds as long as it agrees with most of
    them: one frame it disagrees on is a frame contradicted. Disagreeing with most, one weak model stands against
    the refinement: on the furnished room of held-out seed 217 (photos, plain walls) COLMAP registered 3 of 8
    frames on 59 points, 19-120 deg off the truth; it contradicted three refined frames 1.1-1.3 deg off and
    ended every default run with exit 5.

    Any model, passed or failed, is no witness where it disagrees at all and the refinement is clearly the stronger
    evidence (:func:`_stronger_refinement`; until session 49 only where it disagreed with most frames). On the
    object of held-out seed 252 (photos, 65-deg lens) COLMAP registered 4 of 8 frames on 165 points (failing its
    registration gate), 2.4-9.9 deg off the truth, and contradicted one of the 8 frames the refinement held within
    0.21 deg: every default run ended with exit 5. On the repeated-tile street of held-out seed 261 (drift) COLMAP
    registered 7 of 8 frames on 108 points, passing its gates, 1.3-4.5 deg off the truth, against 8 refined on 9,923
    points within 1.3 deg; it agreed on 4 of 7 and the run ended with exit 5 (without drift it confirmed frames 3.5
    deg off and left out good ones). On the room of held-out seed 242 (photos, 85-deg lens) COLMAP's incremental
    mapper registered 3 of 8 frames in two models, its global mapper 7 on 144 points, two of them 90 deg off; it
    passed its gates, called the model unsuited, and its cameras replaced
    the refinement's (8 of 8 frames on 2,763 points, within 3.1 deg of the model, median 0.07 deg from the truth).
    """
    if colmap is None:
        return ""
    lookalike = _lookalike(refine)
    healthy = _healthy(colmap, witness)
    if lookalike and not healthy:
        return (
            f"COLMAP's model failed its gates ({_failed(witness)}) on look-alike surfaces, where its matches are the "
            "suspect ones: it is not a witness"
        )
    common = refine.registered & colmap.registered
    if common.sum() < options.min_common_images:
        return ""
    comp = compare_poses(
        refine.cam_from_world,
        colmap.cam_from_world,
        refine.names,
        refine.registered,
        ref_registered=colmap.registered,
        options=options.disagreement,
        centers=healthy,
    )
    if not comp.disagreements:
        return ""
    both, share = int(common.sum()), len(comp.disagreements) / int(common.sum())
    if stronger := _stronger_refinement(refine, colmap, ff_cam_from_world, options):
        failed = "" if healthy else f" failed its gates ({_failed(witness)}),"
        return (
            f"COLMAP's model{failed} disagrees with the refined cameras on {len(comp.disagreements)} of the {both} "
            f"frames both hold, and is the weaker evidence: {stronger}; it is not a witness"
        )
    if share <= options.unsuited_share or (healthy and not lookalike):
        return ""
    if not healthy:
        return (
            f"COLMAP's model failed its gates ({_failed(witness)}) and disagrees with the refined cameras on "
            f"{share:.0%} of the {both} frames both hold: one weak model against the refinement's evidence; it is "
            "not a witness"
        )
    return (
        f"on look-alike surfaces COLMAP's model and the refined cameras disagree on {share:.0%} of the frames both "
        "hold: either may sit a pattern's period off, neither checks the other; COLMAP is not a witness"
    )


STRONGER_POINTS = 3.0  # the refinement's 3D points against COLMAP's, for it to be the stronger evidence


def _stronger_refinement(refine: RefineResult, colmap: ColmapResult, ff_cam_from_world, options) -> str:
    """Why the refinement is clearly stronger evidence than COLMAP's model ("" when it is not): it holds every
    frame COLMAP holds, on ``STRONGER_POINTS`` times its 3D points, and its cameras stay within the correction limit
    of the model's on most frames (the model suits the photos by the refinement's own matches; a model wrong on most
    frames is moved far from, or fails to refine)."""
    if ff_cam_from_world is None:
        return ""
    points = len(refine.points_xyz)
    if points < STRONGER_POINTS * max(colmap.num_points, 1):
        return ""
    held = refine.registered
    if (colmap.registered & ~held).any() or held.sum() < options.min_common_images:
        return ""
    turned = rotation_angle_deg(refine.cam_from_world[held, :, :3] @ np.swapaxes(ff_cam_from_world[held, :, :3], 1, 2))
    if np.median(turned) > options.max_correction_deg:
        return ""
    return (
        f"the refinement holds {int(held.sum())} frames on {points} points (COLMAP {colmap.num_registered} on "
        f"{colmap.num_points}) and stays within {np.median(turned):.1f} deg of the model's cameras (median)"
    )


def _failed(witness: GatesResult) -> str:
    """The names of COLMAP's own gates that failed."""
    return ", ".join(v.name for v in witness.verdicts if v.failed and v.name != "depth_coverage")


def _unsuited(
    names: Sequence[str], ff_cam_from_world: np.ndarray, colmap: ColmapResult | None, witness: GatesResult, options
) -> str:
    """Why the model is unsuited ("" if it is not): a healthy COLMAP model disagrees with it on most images."""
    if not _healthy(colmap, witness) or colmap.num_registered < options.min_common_images:
        return ""
    comp = compare_poses(
        ff_cam_from_world,
        colmap.cam_from_world,
        names,
        None,
        ref_registered=colmap.registered,
        estimate="feed-forward",
        reference="COLMAP",
        options=options.disagreement,
    )
    share = len(comp.disagreements) / max(int(colmap.registered.sum()), 1)
    if share <= options.unsuited_share:
        return ""
    return (
        f"the model's cameras disagree with a healthy COLMAP model on {share:.0%} of the images it registered "
        f"(> {options.unsuited_share:.0%}): the model does not suit these photos, COLMAP's cameras are used"
    )
