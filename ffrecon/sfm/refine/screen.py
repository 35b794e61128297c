"""Frames whose model rotation their own verified pairs contradict, found before the adjustment.

The bundle adjustment starts from the model's cameras and is a local method. Where matches are
scarce (a sparse, wide-baseline capture), one frame the model turned far off can pull the whole
chain with it instead of being pulled back: on the wide-baseline scene (seed 7) with frame 1 turned
25 deg, the adjustment bent every frame 5-11 deg from the truth and kept frame 1 near its wrong pose.

Each verified pair carries its own relative rotation (an essential matrix fitted to its SIFT
inliers, :func:`ffrecon.sfm.verified_pairs.relative_rotations`), whatever the cameras' poses, so
each partner of a frame implies a rotation for it: the partner's model rotation turned by the pair's.
A frame is a suspect when at least ``min_agreeing`` partners imply rotations that agree with each
other (within ``max_gap_deg``) and all lie more than ``max_gap_deg`` from the model's, and they hold
more than ``min_share`` of its pairs' inliers. Requiring agreement matters: a pair's measured rotation can
itself be wrong (seed 7's frames 0 and 7 share 19 inliers on flat walls whose essential matrix is
50 deg off), and a frame with one such pair, or one bad partner and one wrong pair, implies
rotations that scatter and is not blamed. Frames are blamed one at a time, the best-supported first,
and a blamed frame's pairs are set aside before the next (a bad partner must not make a good frame
look bad): a bounded loop, one round per frame at most. The agreeing partners' mean is the frame's
rotation as its pairs see it.

This is written here, not taken from a library: pycolmap's view-graph calibration and rotation
averaging (GLOMAP) solve for rotations; this asks which *given* rotations a graph of measured
ones contradicts, a few lines of counting over the pairs.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from ffrecon.checks import check_number
from ffrecon.geometry.poses import camera_centers
from ffrecon.geometry.rotations import chordal_mean, rotation_angle_deg
from ffrecon.sfm.verified_pairs import relative_rotations
from ffrecon.types import Prediction


@dataclass(frozen=True, kw_only=True)
class ScreenOptions:
    enabled: bool = True
    # A pair's measured relative rotation further than this from the model's: the pair is inconsistent.
    # Feed-forward errors are a few degrees; 10 deg matches the evidence's max_correction_deg.
    max_gap_deg: float = 10.0
    min_inliers: int = 15  # essential-matrix inliers of a pair whose relative rotation counts
    # Blame needs more than this share of the frame's pairs, weighed by their inliers, agreeing on another rotation.
    # Counted one pair each, a frame 25 deg off whose two strongest pairs (73 and 126 inliers) agreed within 4 deg
    # of the truth was not blamed for two weak scattered ones (22 and 47; room seed 210, repeated tile, frame 1).
    min_share: float = 0.5
    min_agreeing: int = 2  # ... and at least this many of them (one pair's rotation may itself be wrong)
    min_ray_angle_deg: float = 5.0  # baselines closer to parallel do not place the frame's centre
    # A pair's rotation is fitted to at most this many of its verified matches (0: all). On the looped 500-frame
    # bench scene (4,427 pairs, 676 matches a pair): 28.5 -> 8.2 s, rotations within 0.57 deg of the full fits
    # (median 0.04), far inside max_gap_deg.
    max_matches: int = 128

    def __post_init__(self) -> None:
        check_number("ScreenOptions.max_gap_deg", self.max_gap_deg, low=0, low_open=True, high=180)
        check_number("ScreenOptions.min_inliers", self.min_inliers, low=8, integer=True)
        check_number("ScreenOptions.min_share", self.min_share, low=0, high=1)
        check_number("ScreenOptions.min_agreeing", self.min_agreeing, low=1, integer=True)
        check_number("ScreenOptions.min_ray_angle_deg", self.min_ray_angle_deg, low=0, high=180)
        if self.max_matches:
            check_number("ScreenOptions.max_matches", self.max_matches, low=self.min_inliers, integer=True)


@dataclass(frozen=True)
class PairGap:
    """One verified pair: its measured relative rotation against the one the model's cameras imply."""

    index1: int
    index2: int
    num_inliers: int
    gap_deg: float
    cam2_from_cam1: np.ndarray = field(repr=False)  # [3, 3] the pair's measured relative rotation
    cam1_centre_in_cam2: np.ndarray = field(repr=False)  # [3] unit: the measured baseline's direction


@dataclass(frozen=True)
class Suspect:
    """A frame whose verified pairs contradict its model rotation and agree on another one."""

    index: int
    num_pairs: int  # its verified pairs still counted when it was blamed
    num_agreeing: int  # partners implying the rotation ``rotation``
    gap_deg: float  # angle between that rotation and the model's
    rotation: np.ndarray = field(repr=False)  # [3, 3] cam_from_world rotation its agreeing pairs imply
    # [3] world centre where its agreeing pairs' baselines from the partners' model centres meet; None:
    # they do not meet well enough (nearly parallel, or behind a partner) and the model's centre is kept
    centre: np.ndarray | None = field(repr=False, default=None)

    def to_report(self, names: tuple[str, ...]) -> dict:
        return {
            "name": names[self.index],
            "gap_deg": round(self.gap_deg, 3),
            "agreeing_pairs": self.num_agreeing,
            "pairs": self.num_pairs,
        }


def pair_gaps(db_path: Path, prediction: Prediction, options: ScreenOptions = ScreenOptions()) -> tuple[PairGap, ...]:
    """Every verified pair with at least ``options.min_inliers`` essential-matrix inliers: its measured
    ``cam2_from_cam1`` and the angle (deg) to the model's ``R2 @ R1.T``."""
    names = tuple(prediction.names)
    index = {n: k for k, n in enumerate(names)}
    rotations = prediction.cam_from_world[:, :3, :3]
    out = []
    max_matches = options.max_matches or None
    for pair in relative_rotations(Path(db_path), names, min_inliers=options.min_inliers, max_matches=max_matches):
        if pair.name1 not in index or pair.name2 not in index:
            continue
        i, j = index[pair.name1], index[pair.name2]
        gap = float(rotation_angle_deg(pair.cam2_from_cam1.T @ rotations[j] @ rotations[i].T))
        out.append(PairGap(i, j, pair.num_inliers, gap, pair.cam2_from_cam1, pair.cam1_centre_in_cam2))
    return tuple(out)


def blame(gaps: tuple[PairGap, ...], cam_from_world: np.ndarray, options: ScreenOptions = ScreenOptions()):
    """The frames to blame for the inconsistent pairs (see the module docstring), in the order found.

    Args:
        gaps: the verified pairs; cam_from_world: ``[N, 3, 4]`` the model's cameras.
    Returns:
        ``tuple[Suspect, ...]``.
    """
    remaining = list(gaps)
    found: list[Suspect] = []
    for _ in range(len(cam_from_world)):
        candidates = [_suspect(f, _pairs_of(remaining, f), cam_from_world, options) for f in range(len(cam_from_world))]
        candidates = [c for c in candidates if c is not None]
        if not candidates:
            break
        best = max(candidates, key=lambda c: c.num_agreeing)  # the first of the best supported
        partners = {g.index1 + g.index2 - best.index for g in _pairs_of(remaining, best.index)}
        if any(c.index in partners and c.num_agreeing == best.num_agreeing for c in candidates):
            break  # as well supported a suspect among its partners: which one is off cannot be told
        found.append(best)
        remaining = [g for g in remaining if best.index not in (g.index1, g.index2)]
    return tuple(found)


def _pairs_of(gaps: list[PairGap], frame: int) -> list[PairGap]:
    return [g for g in gaps if frame in (g.index1, g.index2)]


def _suspect(frame: int, pairs: list[PairGap], cam_from_world: np.ndarray, options: ScreenOptions) -> Suspect | None:
    """The frame as a suspect, or None: its partners' implied rotations far from the model's, agreeing."""
    rotations = cam_from_world[:, :, :3]
    far = [g for g in pairs if g.gap_deg > options.max_gap_deg]
    total = sum(g.num_inliers for g in pairs)
    if len(far) < options.min_agreeing or sum(g.num_inliers for g in far) <= options.min_share * total:
        return None
    # R2 = M R1: the frame as camera 1 is implied as M^T R2, as camera 2 as M R1
    implied = np.stack(
        [
            g.cam2_from_cam1.T @ rotations[g.index2] if frame == g.index1 else g.cam2_from_cam1 @ rotations[g.index1]
            for g in far
        ]
    )
    agree = rotation_angle_deg(implied[:, None] @ np.swapaxes(implied[None], -1, -2)) <= options.max_gap_deg
    core = agree[int(np.argmax(agree.sum(1)))]  # [F] the largest group agreeing with one of them
    held = sum(g.num_inliers for g, c in zip(far, core) if c)  # pairs weigh by their inliers, not one each
    if core.sum() < options.min_agreeing or held <= options.min_share * total:
        return None
    mean = chordal_mean(implied[core])
    gap = float(rotation_angle_deg(mean @ rotations[frame].T))
    if gap <= options.max_gap_deg:
        return None
    centre = _meeting_point(frame, [g for g, c in zip(far, core) if c], mean, cam_from_world, options)
    return Suspect(frame, len(pairs), int(core.sum()), gap, mean, centre)


def _meeting_point(frame: int, pairs: list[PairGap], rotation: np.ndarray, cam_from_world: np.ndarray, options):
    """``[3]`` where the rays from the partners' model centres along the pairs' measured baselines meet
    (least squares), or None when they are within ``options.min_ray_angle_deg`` of parallel or the point
    lies behind a partner's ray."""
    origins, directions = [], []
    for g in pairs:
        if frame == g.index1:  # the frame is camera 1: seen from the partner (camera 2) along the baseline
            partner, direction = g.index2, cam_from_world[g.index2, :, :3].T @ g.cam1_centre_in_cam2
        else:  # the partner is camera 1, seen from the frame: the frame lies the opposite way from it
            partner, direction = g.index1, -rotation.T @ g.cam1_centre_in_cam2
        origins.append(camera_centers(cam_from_world[partner]))
        directions.append(direction / np.linalg.norm(direction))
    origins, directions = np.stack(origins), np.stack(directions)
    spread = _widest_angle_deg(directions)
    if spread < options.min_ray_angle_deg:
        return None
    across = np.eye(3)[None] - directions[:, :, None] * directions[:, None, :]  # [P, 3, 3] off-ray projections
    centre = np.linalg.solve(across.sum(0), np.einsum("pij,pj->i", across, origins))
    ahead = np.einsum("pi,pi->p", centre - origins, directions)
    return centre if np.all(ahead > 0) else None


def _widest_angle_deg(directions: np.ndarray) -> float:
    """The largest angle (deg) between any two of ``[P, 3]`` unit vectors."""
    cosines = np.clip(directions @ directions.T, -1.0, 1.0)
    return float(np.degrees(np.arccos(cosines.min())))


def screen_rotations(db_path: Path, prediction: Prediction, options: ScreenOptions = ScreenOptions()):
    """The frames whose verified pairs contradict their model rotation: ``(suspects, gaps)``."""
    if not options.enabled:
        return (), ()
    gaps = pair_gaps(db_path, prediction, options)
    return blame(gaps, prediction.cam_from_world, options), gaps


def reseeded(prediction: Prediction, suspects: tuple[Suspect, ...]) -> Prediction:
    """The prediction with each suspect's pose replaced by the one its pairs imply: their rotation, and
    their centre where the baselines meet (the model's centre otherwise)."""
    if not suspects:
        return prediction
    cam_from_world = prediction.cam_from_world.copy()
    for s in suspects:
        centre = camera_centers(cam_from_world[s.index]) if s.centre is None else s.centre
        cam_from_world[s.index] = np.concatenate([s.rotation, (-s.rotation @ centre)[:, None]], axis=1)
    return dataclasses.replace(prediction, cam_from_world=cam_from_world)


def drop_contradicting_pairs(
    db_path: Path, prediction: Prediction, max_gap_deg: float, options: ScreenOptions = ScreenOptions()
) -> tuple[PairGap, ...]:
    """Delete the verified geometry of every pair whose measured relative rotation lies more than
    ``max_gap_deg`` from the model's; returns those pairs.

    For look-alike surfaces only (matches guided by the model, :mod:`ffrecon.sfm.refine.guided`): there a
    pair's matches can all sit one period of the pattern off, and such pairs agree with each other,
    since one period is one rotation. On the repeated-texture street (seed 201), five of the seven
    pairs between the even and the odd frames did, 9-20 deg from the truth, and the adjustment turned
    one group 16 deg against the other at 0.70 px. Without them (the model's own error is a few
    degrees) it lands at 0.1 deg. A frame whose every pair is dropped keeps no matches: look-alikes
    cannot check it, whatever its pairs say.
    """
    gaps = [g for g in pair_gaps(db_path, prediction, options) if g.gap_deg > max_gap_deg]
    if not gaps:
        return ()
    db = pycolmap.Database.open(str(db_path))
    try:
        id_of = {image.name: image.image_id for image in db.read_all_images()}
        for g in gaps:
            a, b = id_of[prediction.names[g.index1]], id_of[prediction.names[g.index2]]
            if db.exists_two_view_geometry(a, b):
                db.delete_two_view_geometry(a, b)
    finally:
        db.close()
    return tuple(gaps)
