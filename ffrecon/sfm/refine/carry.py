"""Frames the refinement left out, carried along with the refined frames near them.

The refined cameras live in the model's world (:func:`ffrecon.sfm.refine.passes.sim3_to_ff_frame`), but they have
shed the model's errors relative to one another; a frame left out of the adjustment keeps the model's camera there.
Where the model's error is independent per frame that is the best guess, but where it drifts along the path, the
frames left out keep the drift their refined neighbours lost, and no single alignment to the truth fits both
(held-out room seed 310, drift: five refined frames 0.05-0.27 deg off among themselves, three left out at the
model's 2.7-3.9 deg, the whole model aligned at once put the refined ones 2.2 deg off).

Each refined frame ``o`` received a correction ``A_o = R_model_o^T R_refined_o`` (a rotation in its own camera
frame) and a centre: a frame ``u`` carried by it keeps the model's relative pose to ``o`` (rotation
``R_model_u A_o``, centre ``c_refined_o + A_o^T R_model_o (c_model_u - c_model_o)``). A frame takes the weighted
mean of its carries over the refined frames, the weights a Gaussian of the model's centre distances with one of a
few widths (multiples of the frames' median spacing, or infinite: one correction for all), or no carry (the
model's camera as it is). Which of these is decided by the refined frames themselves: each is predicted from the
others with every choice, leave-one-out; the width with the smallest mean rotation error places the frames left
out if it predicts them clearly better than no carry (by two standard errors of the paired differences). No
threshold is tuned: drift makes the local choices predict best, independent noise none.

Written here by hand: a kernel-weighted chordal mean of rotations (:func:`ffrecon.geometry.rotations.nearest_rotation`)
with leave-one-out selection of its width is a few lines of numpy; no library used by ffrecon offers it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ffrecon.geometry.poses import camera_centers
from ffrecon.geometry.rotations import nearest_rotation, rotation_angle_deg

WIDTHS = (1.0, 2.0, 4.0, np.inf)  # kernel widths, in the frames' median spacing of the model's centres
MIN_REFINED = 3  # refined frames needed to choose by leave-one-out (with two, each predicts the other alone)
_ROWS = 256  # rows of the weight matrix built at once: memory stays O(rows x refined frames)


@dataclass(frozen=True)
class Carry:
    """How the frames left out were placed: ``width`` (in median spacings; inf: one correction for all; None: the
    model's cameras as they are) and each choice's leave-one-out mean rotation error (deg) on the refined frames."""

    width: float | None
    loo_error_deg: dict[str, float]
    carried: tuple[int, ...]  # the frames moved

    @property
    def scheme(self) -> str:
        """``model`` (no carry), ``global`` (one correction for all) or ``local W`` (W median spacings)."""
        return _label(self.width)

    def to_report(self, names: tuple[str, ...]) -> dict:
        return {
            "scheme": self.scheme,
            "leave_one_out_rotation_deg": {k: round(v, 4) for k, v in self.loo_error_deg.items()},
            "carried": [names[k] for k in self.carried],
        }


def _label(width: float | None) -> str:
    if width is None:
        return "model"
    return "global" if np.isinf(width) else f"local {width:g}"


def carry_left_out(
    model_cam_from_world: np.ndarray, refined_cam_from_world: np.ndarray, refined: np.ndarray
) -> tuple[np.ndarray, Carry | None]:
    """The cameras with the frames not ``refined`` carried along (see the module's docstring).

    Args:
        model_cam_from_world: ``[N, 3, 4]`` the model's cameras (OpenCV cam_from_world).
        refined_cam_from_world: ``[N, 3, 4]`` the refined cameras in the model's world (only ``refined`` read).
        refined: ``[N]`` bool, the frames the adjustment refined.
    Returns:
        ``[N, 3, 4]``: refined frames as refined, the others carried (or the model's), and the :class:`Carry`
        (None when nothing was chosen: no frame left out, or fewer than ``MIN_REFINED`` refined frames).
    """
    refined = np.asarray(refined, bool)
    out = np.where(refined[:, None, None], refined_cam_from_world, model_cam_from_world)
    left = np.flatnonzero(~refined)
    ref = np.flatnonzero(refined)
    if len(left) == 0 or len(ref) < MIN_REFINED:
        return out, None
    centres = camera_centers(model_cam_from_world)
    if not (np.isfinite(centres).all() and np.isfinite(refined_cam_from_world[ref]).all()):
        return out, None
    fields = _Corrections(model_cam_from_world[ref], refined_cam_from_world[ref])
    spacing = _median_spacing(centres)
    widths = [w for w in WIDTHS if np.isinf(w) or spacing > 0]
    loo = {"model": rotation_angle_deg(fields.rotation)}
    for w in widths:
        loo[_label(w)] = fields.leave_one_out_deg(centres[ref], w * spacing)
    errors = {k: float(np.mean(v)) for k, v in loo.items()}
    best = min(widths, key=lambda w: errors[_label(w)])
    if not _clearly_better(loo[_label(best)], loo["model"]):
        return out, Carry(None, errors, ())
    width = best
    out[left] = fields.carry(model_cam_from_world[left], centres[ref], centres[left], width * spacing)
    return out, Carry(width, errors, tuple(int(k) for k in left))


def _clearly_better(errors: np.ndarray, baseline: np.ndarray) -> bool:
    """Whether per-frame ``errors`` beat ``baseline`` (the same frames) by more than two standard errors of their
    mean paired difference: with a few refined frames and independent noise, the best of several choices beats
    the model's cameras by chance (a carry then adds the neighbours' noise to the frame's own)."""
    diff = baseline - errors
    if len(diff) < 2:
        return False
    return bool(diff.mean() > 2 * diff.std(ddof=1) / np.sqrt(len(diff)))


def _median_spacing(centres: np.ndarray) -> float:
    """The median over frames of the distance to the nearest other frame's centre (0 when they coincide)."""
    nearest = []
    for rows in np.array_split(np.arange(len(centres)), max(1, len(centres) // _ROWS)):  # O(rows x frames) memory
        d = np.linalg.norm(centres[rows, None] - centres[None], axis=-1)
        d[np.arange(len(rows)), rows] = np.inf
        nearest.append(d.min(axis=1))
    return float(np.median(np.concatenate(nearest)))


class _Corrections:
    """The refined frames' corrections: rotations ``A_o = R_model^T R_refined`` ``[R, 3, 3]``, and the affine
    carry of a centre, ``c -> b_o + B_o c`` with ``B_o = A_o^T``, ``b_o = c_refined_o - B_o c_model_o``."""

    def __init__(self, model: np.ndarray, refined: np.ndarray) -> None:
        self.rotation = np.swapaxes(model[:, :, :3], 1, 2) @ refined[:, :, :3]
        self.centre_map = np.swapaxes(self.rotation, 1, 2)
        self.centre_offset = camera_centers(refined) - np.einsum("rij,rj->ri", self.centre_map, camera_centers(model))

    def _weights(self, at: np.ndarray, centres: np.ndarray, width: float, own: np.ndarray | None) -> np.ndarray:
        """``[M, R]`` Gaussian weights of the refined frames for points ``at`` ``[M, 3]`` (zero on ``own``, each
        row's own refined frame, for leave-one-out); relative to each row's nearest, so none underflows."""
        d2 = np.sum((at[:, None] - centres[None]) ** 2, axis=-1)
        if own is not None:
            d2[np.arange(len(at)), own] = np.inf
        if np.isinf(width):
            return np.where(np.isfinite(d2), 1.0, 0.0)
        return np.exp(-(d2 - d2.min(axis=1, keepdims=True)) / (2 * width**2))

    def _mean_rotation(self, weights: np.ndarray) -> np.ndarray:
        """``[M, 3, 3]`` the weighted chordal mean of the corrections per row of ``weights``."""
        return nearest_rotation(np.einsum("mr,rij->mij", weights, self.rotation))

    def leave_one_out_deg(self, centres: np.ndarray, width: float) -> np.ndarray:
        """``[R]`` each refined frame's rotation error (deg) when predicted from the others' corrections."""
        out = []
        for rows in np.array_split(np.arange(len(centres)), max(1, len(centres) // _ROWS)):
            mean = self._mean_rotation(self._weights(centres[rows], centres, width, rows))
            out.append(rotation_angle_deg(np.swapaxes(self.rotation[rows], 1, 2) @ mean))
        return np.concatenate(out)

    def carry(self, model: np.ndarray, centres: np.ndarray, at: np.ndarray, width: float) -> np.ndarray:
        """``[M, 3, 4]`` cameras ``model`` (their centres ``at``) carried by the weighted corrections."""
        out = np.empty_like(model)
        for rows in np.array_split(np.arange(len(at)), max(1, len(at) // _ROWS)):
            w = self._weights(at[rows], centres, width, None)
            w = w / w.sum(axis=1, keepdims=True)
            rot = model[rows, :, :3] @ self._mean_rotation(w)
            centre = np.einsum("mr,ri->mi", w, self.centre_offset) + np.einsum(
                "mr,rij,mj->mi", w, self.centre_map, at[rows]
            )
            out[rows, :, :3] = rot
            out[rows, :, 3] = -np.einsum("mij,mj->mi", rot, centre)
        return out
