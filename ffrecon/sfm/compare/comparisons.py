"""The pose-comparison stage: every estimate against every reference.

Estimates are the feed-forward cameras, COLMAP's and the refined ones; references are COLMAP (the
cross-check), and ground truth or a ``--reference`` COLMAP model when given. The metrics are the
field's (docs/contracts.md, "Pose error"); see :func:`ffrecon.sfm.compare.poses.compare_poses`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from ffrecon.checks import GB, check_model_files
from ffrecon.colmap_io import cam_from_world_by_name, is_model_dir
from ffrecon.errors import InputError
from ffrecon.formats.ground_truth import ground_truth_poses
from ffrecon.geometry.poses import up_from_cameras
from ffrecon.sfm.compare.poses import PoseComparison, compare_poses
from ffrecon.sfm.crosscheck.run import ColmapResult
from ffrecon.sfm.refine.options import RefineResult
from ffrecon.types import Skipped

# Reference poses by label: (cam_from_world [N, 3, 4], has a pose [N] bool), over the run's names.
References = dict[str, tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class ComparisonsResult:
    """Pose error of every estimate against every reference, and which set the plots use.

    ``primary`` are the comparisons against the most trustworthy reference (ground truth, a
    reference model, else COLMAP); ``up`` is that reference's mean camera up direction.
    """

    comparisons: tuple[PoseComparison, ...]
    primary: tuple[PoseComparison, ...]
    up: np.ndarray | None  # [3] in the primary reference's world frame; None without comparisons

    def by_label(self, estimate: str, reference: str) -> PoseComparison | None:
        """The comparison of ``estimate`` against ``reference`` (e.g. "feed-forward", "COLMAP")."""
        return next((c for c in self.comparisons if (c.estimate, c.reference) == (estimate, reference)), None)


def check_references(ground_truth: Path | None, reference: Path | None) -> None:
    """Raise InputError unless the references load: called before any work, so a bad ``--reference`` stops
    the run in seconds rather than after COLMAP, and read again by :func:`load_references` at the end."""
    if ground_truth is not None and not (Path(ground_truth) / "ground_truth.json").is_file():
        raise InputError(
            f"ground truth {ground_truth} is not a synthetic scene folder (no ground_truth.json)",
            "set RunOptions.ground_truth to a folder written by ffrecon.synthetic.write_scene, or None",
        )
    if reference is None:
        return
    ref = Path(reference)
    fix = "pass --reference the folder of a COLMAP model (cameras, images, points3D .bin or .txt; e.g. sparse/0)"
    if not is_model_dir(ref):
        inside = [p for p in (ref / "sparse" / "0", ref / "0", ref.parent) if is_model_dir(p)]
        what = "is not a COLMAP model folder (no images.bin or images.txt)" if ref.exists() else "does not exist"
        raise InputError(f"--reference {ref} {what}", f"pass --reference {inside[0]}" if inside else fix)
    check_model_files("--reference", ref, limit_bytes=32 * GB, fix=fix)  # COLMAP would hang on a FIFO
    try:
        registered = pycolmap.Reconstruction(str(ref)).num_reg_images()
    except Exception as err:  # pycolmap raises ValueError, RuntimeError or MemoryError on bad files
        raise InputError(f"--reference {ref}: COLMAP cannot read the model ({err})", fix) from None
    if registered == 0:
        raise InputError(f"--reference {ref} has no registered images to score the cameras against", fix)


def load_references(
    ground_truth: Path | None,
    reference: Path | None,
    names: Sequence[str],
    given: Sequence[np.ndarray | None] = (),
) -> References:
    """Ground truth of a synthetic scene folder, a reference COLMAP model and/or the poses the user gave
    (``--poses``: per frame, None where not given), over ``names``."""
    refs: References = {}
    if any(p is not None for p in given):
        have = np.array([p is not None for p in given])
        refs["given poses"] = (np.stack([np.eye(3, 4) if p is None else p for p in given]), have)
    if ground_truth is not None:
        truth_names, truth_poses = ground_truth_poses(Path(ground_truth))
        index = {n: k for k, n in enumerate(truth_names)}
        have = np.array([n in index for n in names])
        poses = np.stack([truth_poses[index[n]] if n in index else np.eye(3, 4) for n in names])
        refs["ground truth"] = (poses, have)
    if reference is not None:
        refs["reference model"] = cam_from_world_by_name(pycolmap.Reconstruction(str(reference)), list(names))
    return refs


def run_comparisons(names: Sequence[str], estimates: References, references: References) -> ComparisonsResult:
    """Compare the estimates with COLMAP (feed-forward only) and with every given reference.

    Args:
        names: the run's image names, in order.
        estimates: by label, e.g. ``{"feed-forward": ..., "COLMAP": ..., "refined": ...}``; a
            "COLMAP" entry is also the cross-check reference of the feed-forward cameras.
        references: ground truth and/or a reference model (:func:`load_references`).
    """
    names = list(names)
    comparisons: list[PoseComparison] = []
    if "COLMAP" in estimates and "feed-forward" in estimates:
        poses, reg = estimates["COLMAP"]
        ff_poses, ff_reg = estimates["feed-forward"]
        comparisons.append(
            compare_poses(
                ff_poses, poses, names, ff_reg, ref_registered=reg, estimate="feed-forward", reference="COLMAP"
            )
        )
    primary: list[PoseComparison] = []
    for ref_label, (ref_poses, ref_have) in references.items():
        group = [
            compare_poses(poses, ref_poses, names, reg, ref_registered=ref_have, estimate=label, reference=ref_label)
            for label, (poses, reg) in estimates.items()
        ]
        comparisons += group
        primary = primary or group
    primary = primary or comparisons[:1]
    up = None
    if primary:
        label = primary[0].reference
        up = up_from_cameras(references[label][0] if label in references else estimates["COLMAP"][0])
    return ComparisonsResult(tuple(comparisons), tuple(primary), up)


def pose_estimates(
    model_poses: np.ndarray | None, colmap: ColmapResult | Skipped, refine: RefineResult | Skipped
) -> References:
    """The run's cameras to compare, by label: the model's own, COLMAP's (two images or more) and the refined."""
    estimates: References = {}
    if model_poses is not None:
        estimates["feed-forward"] = (model_poses, np.ones(len(model_poses), bool))
    if isinstance(colmap, ColmapResult) and colmap.num_registered >= 2:
        estimates["COLMAP"] = (colmap.cam_from_world, colmap.registered)
    if isinstance(refine, RefineResult):
        estimates["refined"] = (refine.cam_from_world, refine.registered)
    return estimates


def comparison_skip_reason(
    model_poses: np.ndarray | None, colmap: ColmapResult | Skipped, refine: RefineResult | Skipped, references: bool
) -> str | None:
    """Why there is nothing to compare (fewer than two sets of cameras and no ``references`` given), or None."""
    if len(pose_estimates(model_poses, colmap, refine)) >= 2 or references:
        return None
    if model_poses is None:
        return "no model, and no ground truth or --reference: COLMAP's cameras are the only ones"
    state = "did not run" if isinstance(colmap, Skipped) else "registered fewer than two images"
    return f"no reference cameras: the COLMAP cross-check {state} and no ground truth or --reference"
