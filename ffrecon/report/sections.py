"""report.json's sections of the stages that give more than their result's ``to_report()``: each takes the run's
:class:`~ffrecon.results.RunResults` and returns its entries (key -> data), as :attr:`ffrecon.state.Stage.report`
asks. The stage list (:mod:`ffrecon.stages`) names each stage's; :func:`ffrecon.report.build.build_report` loops
over the stages."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ffrecon.export.stage import ExportsResult
from ffrecon.models.stage import FeedForwardResult
from ffrecon.results import RunResults
from ffrecon.sfm.refine.options import RefineResult
from ffrecon.sfm.verify.verdicts import CameraStatus, EvidenceResult, FrameVerdict
from ffrecon.state import report_section
from ffrecon.types import Skipped


def nothing(results: RunResults) -> dict:
    """No entry: the stage's result is reported by the stages that read it."""
    return {}


def capture_entries(results: RunResults) -> dict:
    return {"inputs": results.capture.to_report()}


def feedforward_entries(results: RunResults) -> dict:
    return {"feedforward": report_section(results.feedforward), "intrinsics": _intrinsics(results)}


def gates_entries(results: RunResults) -> dict:
    return {"gates": report_section(results.gates, lambda g: [v.to_report() for v in g.verdicts])}


def evidence_entries(results: RunResults) -> dict:
    return {"evidence": report_section(results.evidence, _evidence)}


def comparisons_entries(results: RunResults) -> dict:
    errors, plot = _pose_section(results)
    return {"pose_errors": errors, "pose_plot": plot}


def exports_entries(results: RunResults) -> dict:
    return {"exports": report_section(results.exports, lambda ex: _exports(ex, results.out_dir))}


def _exports(ex: ExportsResult, out: Path) -> dict:
    def rel(p: Path | None) -> str | None:
        return None if p is None else str(Path(p).relative_to(out))

    return {
        "points_ply": rel(ex.points_ply),
        "num_points": ex.num_points,
        "points": ex.points_from,
        "transforms_json": rel(ex.transforms_json),
        "mesh": {"ply": rel(ex.mesh_ply), "glb": rel(ex.mesh_glb), "about": ex.mesh_about} if ex.mesh_ply else None,
        "cameras": ex.cameras_from,
        "not_written": dict(ex.not_written),  # file -> why (an empty cloud: no points.ply, no mesh)
    }


def _evidence(evidence: EvidenceResult) -> dict:
    return {
        "gates": [v.to_report() for v in evidence.gates.verdicts],
        "per_image": [e.to_report() for e in evidence.per_image],
        "model_unsuited": evidence.model_unsuited,
        "unsuited_reason": evidence.unsuited_reason,
        "refinement_set_aside": evidence.refinement_set_aside,
        "counts": {s.value: evidence.count(s) for s in CameraStatus},
        "verdicts": {v.value: list(evidence.of(v)) for v in FrameVerdict},
    }


def _pose_section(results: RunResults) -> tuple[dict, dict | None]:
    """``(pose_errors by key, data for the pose plots)``; the plot data follows the primary reference."""
    comps = results.comparisons
    if isinstance(comps, Skipped):
        return {}, None
    errors = {
        f"{c.estimate}_vs_{c.reference}".replace(" ", "_").replace("-", "").lower(): c.to_report()
        for c in comps.comparisons
    }
    if not comps.primary:
        return errors, None
    ref = comps.primary[0]
    plot = {
        "reference": ref.reference,
        "up": comps.up,
        "names": list(ref.names),
        "reference_centers": ref.reference_centers,
        "aligned_centers": {c.estimate: c.aligned_centers for c in comps.primary},
        "rotation_deg": {c.estimate: c.per_image_rotation_deg for c in comps.primary},
        "center_error": {c.estimate: c.per_image_center_error for c in comps.primary},
        "disagreeing": sorted({d for c in comps.primary for d in c.disagreeing}, key=list(ref.names).index),
    }
    return errors, plot


def _intrinsics(results: RunResults) -> dict | None:
    """The given intrinsics (--intrinsics) beside the model's own estimate and the final cameras' (median focal
    lengths, px, and relative differences); None when none were given."""
    capture = results.capture
    if not capture.known_cameras:
        return None
    given = float(np.median([c.fx for c in capture.known_cameras]))
    ff = results.feedforward
    model = [c.fx for c in ff.model_cameras] if isinstance(ff, FeedForwardResult) and ff.model_cameras else []
    final = []
    if isinstance(results.refine, RefineResult):
        final = [c.fx for c, r in zip(results.refine.cameras, results.refine.registered) if r]
    elif isinstance(ff, FeedForwardResult):
        final = [c.fx for c in ff.prediction.cameras]

    def vs_given(values: list[float]) -> dict:
        median = float(np.median(values)) if values else None
        return {"focal_px": median, "vs_given": None if median is None else median / given - 1.0}

    return {
        "file": str(capture.known_file) if capture.known_file else None,
        "fixed": capture.intrinsics_fixed,
        "given_focal_px": given,
        "model": vs_given(model),
        "final": vs_given(final),
    }
