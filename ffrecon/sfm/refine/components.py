"""Parts of the refined model that share no point, each placed on the model's cameras of its own frames.

A bundle adjustment fixes how frames sit relative to each other only through the points they share. When the
refined frames fall into parts that share none (on look-alike surfaces, where the pairs between the parts were
dropped as a pattern's period off), each part is rigid inside but free as a whole: the adjustment fixes the
gauge of one part, and every other part ends wherever its first frames pulled it. Placing the whole model on
the prediction by one similarity then leaves each other part as far off as the frames that anchored it.

Here every part is moved into the prediction's world by its own similarity, fitted to the model's cameras of
its frames (:func:`~ffrecon.geometry.alignment.camera_sim3`): where nothing but the model relates the parts,
their relative placement is the model's, averaged over each part's frames.

Measured on the street family, seed 207 (repeated tile, 50-deg lens, independent 2.5-deg errors): parts of 2, 3
and 3 frames, each within 0.2-1.2 deg inside; placed as one model the frames ended 0.2-3.3 deg off (median
3.0, the model's 2.6), the three parts 3-6 deg apart.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
import pycolmap

from ffrecon.colmap_io import cam_from_world_by_name
from ffrecon.geometry.alignment import Sim3, camera_sim3
from ffrecon.geometry.poses import camera_centers
from ffrecon.geometry.rotations import matrix_to_quat_xyzw
from ffrecon.sfm.refine.links import group_labels, shared_points
from ffrecon.sfm.refine.options import WeakFrame, WeakReason

logger = logging.getLogger(__name__)

# Frames sharing fewer 3D points than this are not held together: three points not on a line fix a similarity.
MIN_SHARED_POINTS = 3
# A part is placed on the model's cameras of its frames within this of their medoid (camera_sim3's max_angle_deg):
# the model's errors are a few degrees (2.5 per frame: two frames ~3.5 apart, ~7 at worst); a frame further from
# the others is one the model turned far off, and it must not tilt its part (held-out room 364: a part of three
# frames, one 25 deg off, placed 8 deg off; every final camera 3.2-6.3 deg off, the model's median 2.0)
MAX_PLACING_ANGLE_DEG = 10.0


def parts(rec: pycolmap.Reconstruction) -> list[list[int]]:
    """The registered images of ``rec`` grouped by shared points (at least ``MIN_SHARED_POINTS`` between two
    frames join them), largest part first; image ids in increasing order."""
    registered = sorted(rec.reg_image_ids())
    joined = np.argwhere(np.triu(shared_points(rec, registered) >= MIN_SHARED_POINTS, 1))
    groups: dict[int, list[int]] = {}
    for label, image_id in zip(group_labels(len(registered), joined.tolist()), registered):
        groups.setdefault(label, []).append(image_id)
    return sorted(groups.values(), key=lambda g: (-len(g), g[0]))


def place_parts(rec: pycolmap.Reconstruction, names: Sequence[str], ff_cam_from_world: np.ndarray) -> list[Sim3]:
    """Move each part of ``rec`` (in place) into the prediction's world by its own similarity, fitted to the
    model's cameras ``ff_cam_from_world`` ``[N, 3, 4]`` (in the order of ``names``) of its frames.

    Returns the similarities ``ff_from_refined``, one per part, largest part first; nothing moves (and the
    list is empty) when the model is one part.
    """
    groups = parts(rec)
    if len(groups) < 2:
        return []
    index = {n: k for k, n in enumerate(names)}
    image_part = {image_id: p for p, group in enumerate(groups) for image_id in group}
    point_part, straddling = {}, []
    for point_id, point in rec.points3D.items():
        seen = {image_part[e.image_id] for e in point.track.elements if e.image_id in image_part}
        if len(seen) == 1:
            point_part[point_id] = seen.pop()
        else:  # seen by frames of two parts (fewer points than join them): right in neither once they move
            straddling.append(point_id)
    for point_id in straddling:
        rec.delete_point3D(point_id)
    sims = []
    for p, group in enumerate(groups):
        group_names = [rec.image(i).name for i in group]
        refined, _ = cam_from_world_by_name(rec, group_names)
        sim = camera_sim3(refined, ff_cam_from_world[[index[n] for n in group_names]], MAX_PLACING_ANGLE_DEG)
        if p > 0 and (len(group) < 2 or not (np.isfinite(sim.scale) and sim.scale > 0)):
            sim = sims[0]  # one frame, or centres that fix no scale: it moves with the largest part
        _move(rec, group, [q for q, part in point_part.items() if part == p], sim)
        sims.append(sim)
    logger.info(
        "the refined frames form %d parts that share no point (%s): each placed on the model's cameras of its frames",
        len(groups),
        "; ".join(", ".join(rec.image(i).name for i in g) for g in groups),
    )
    return sims


def hold_apart(rec: pycolmap.Reconstruction, groups: Sequence[Sequence[str]]) -> int:
    """Delete the 3D points of ``rec`` that frames of two of ``groups`` (of names) both see, so that the groups
    become parts that :func:`place_parts` places each on its own; returns how many points were deleted."""
    group_of = {rec.find_image_with_name(n).image_id: g for g, names in enumerate(groups) for n in names}
    straddling = [
        point_id
        for point_id, point in rec.points3D.items()
        if len({group_of[e.image_id] for e in point.track.elements if e.image_id in group_of}) > 1
    ]
    for point_id in straddling:
        rec.delete_point3D(point_id)
    return len(straddling)


def _move(rec: pycolmap.Reconstruction, image_ids: Sequence[int], point_ids: Sequence[int], sim: Sim3) -> None:
    """Apply ``ff_from_refined`` ``sim`` to some images' poses and some points of ``rec``.

    With ``x_ff = s R x + t``: ``cam_from_ff = [Rc R^T | s tc - Rc R^T t]`` for ``cam_from_refined = [Rc | tc]``
    (pycolmap's ``Reconstruction.transform`` moves the whole model; a part needs its own)."""
    for image_id in image_ids:
        frame = rec.frame(rec.image(image_id).frame_id)
        old = frame.rig_from_world.matrix()
        rotation = old[:, :3] @ sim.rotation.T
        translation = sim.scale * old[:, 3] - rotation @ sim.translation
        frame.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(matrix_to_quat_xyzw(rotation)), translation)
    for point_id in point_ids:
        rec.point3D(point_id).xyz = sim.apply(np.asarray(rec.point3D(point_id).xyz))


def lost_frames(rec: pycolmap.Reconstruction, names: Sequence[str], ff_cam_from_world: np.ndarray) -> list[WeakFrame]:
    """Deregister the frames of ``rec`` (already in the prediction's world) whose centre ended further from the
    model's centre than the model's cameras' extent (the largest distance between two of its centres).

    An adjustment can hold a frame's rotation and lose its position: on the repeated-tile street (tuning seed
    203, drift, ``--quick``) a frame held by one planar pair ended 3,800 units from the others (extent 1.9) at
    2.4 px; written to ``sparse/0`` that camera would sit kilometres off. Such a frame keeps the model's camera
    and is judged as any frame the refinement did not hold.
    """
    centres = camera_centers(ff_cam_from_world)
    extent = float(np.max(np.linalg.norm(centres[:, None] - centres[None], axis=-1))) if len(centres) > 1 else 0.0
    index = {n: k for k, n in enumerate(names)}
    out = []
    for image_id in sorted(rec.reg_image_ids()):
        image = rec.image(image_id)
        moved = float(np.linalg.norm(np.asarray(image.projection_center()) - centres[index[image.name]]))
        if extent > 0 and moved > extent:
            out.append(WeakFrame(image.name, WeakReason.LOST_CENTRE, int(round(100 * moved / extent)), 100))
            rec.deregister_frame(image.frame_id)
    if out:
        logger.warning("frames whose refined position was lost, left to the evidence: %s", [w.name for w in out])
    return out
