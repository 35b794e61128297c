"""COLMAP cross-check, feed-forward-seeded bundle adjustment, verification gates, pose comparison.

One subpackage per subsystem: ``crosscheck`` (COLMAP's run and the gates on its model), ``refine`` (the
refinement seeded by the model), ``verify`` (the evidence on the final cameras), ``compare`` (pose metrics);
``features`` and ``verified_pairs`` are the SIFT database and verified pairs they share.

Stage functions (one per stage, typed in and out):

- :func:`ffrecon.sfm.crosscheck.run.run_colmap`: plain COLMAP on the images -> ``OUT/crosscheck/sparse/0``.
- :func:`ffrecon.sfm.crosscheck.gates.run_gates`: verdicts, and whether they stop the run (``GatesResult.blocking``).
- :func:`ffrecon.sfm.compare.poses.compare_poses`: section-5 metrics and the images that disagree.
- :func:`ffrecon.sfm.refine.run.run_refine`: refinement seeded by the prediction -> ``OUT/sparse/0``.
"""

from ffrecon.sfm.compare.poses import DisagreementOptions, PoseComparison, compare_models, compare_poses
from ffrecon.sfm.crosscheck.gate_types import FailureCause, GateOptions, GatesResult, GateStatus, GateVerdict
from ffrecon.sfm.crosscheck.gates import evaluate_gates, run_gates
from ffrecon.sfm.crosscheck.options import CameraSharing, ColmapOptions, MapperKind, PairingMode
from ffrecon.sfm.crosscheck.run import ColmapResult, ColmapStatus, run_colmap
from ffrecon.sfm.refine.options import RefineInputs, RefineOptions, RefineResult, RefineStatus, WeakFrame, WeakReason
from ffrecon.sfm.refine.run import run_refine

__all__ = [
    "CameraSharing",
    "ColmapOptions",
    "ColmapResult",
    "ColmapStatus",
    "DisagreementOptions",
    "FailureCause",
    "GateOptions",
    "GateStatus",
    "GateVerdict",
    "GatesResult",
    "MapperKind",
    "PairingMode",
    "PoseComparison",
    "RefineInputs",
    "RefineOptions",
    "RefineResult",
    "RefineStatus",
    "WeakFrame",
    "WeakReason",
    "compare_models",
    "compare_poses",
    "evaluate_gates",
    "run_gates",
    "run_colmap",
    "run_refine",
]
