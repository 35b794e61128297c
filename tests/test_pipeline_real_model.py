"""Real photos with a (simulated) model: lund with 2.5 deg / 3 % pose noise, refined back to the reference.

No weights can be downloaded, so the model is ffrecon's simulated VGGT-contract model built from a
no-model run's COLMAP reconstruction of the same photos (:mod:`ffrecon.synthetic.real_scene`): its
cameras are that reference plus injected error, its depth the reference's sparse points densified. The
run with the model must bring the cameras back to the reference (the refinement uses the real photos'
features, not the model's depth), and the report must show which images COLMAP confirmed.

The photos are used at their full size (1024 x 768): at 640 px lund's reconstruction is too weakly
determined for a 0.2 deg comparison (docs/pipeline.md, "Known limit").
"""

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import onnx
import pytest

from ffrecon.pipeline import RunOptions, run
from ffrecon.sfm.verify.verdicts import CameraStatus, FrameVerdict
from ffrecon.splat.stage import SplatOptions
from ffrecon.synthetic.real_scene import real_scene_from_colmap
from ffrecon.synthetic.simulated_model import SimulationOptions, build_simulated_vggt

LUND = Path(__file__).resolve().parents[2] / "shared" / "data" / "lund"
NOISE = SimulationOptions(rotation_noise_deg=2.5, translation_noise=0.03, seed=7)

pytestmark = [
    pytest.mark.slow,  # about three minutes on 2 cores
    pytest.mark.skipif(len(list(LUND.glob("*.jpg"))) < 29, reason=f"the real capture is not at {LUND}"),
]


@pytest.fixture(scope="module")
def lund_runs(tmp_path_factory):
    """The no-model reference run, the simulated model built from it, and the run with that model."""
    tmp = tmp_path_factory.mktemp("runs")
    no_splat = SplatOptions(enabled=False)
    reference = run(LUND, tmp / "reference", None, RunOptions(splat=no_splat))
    ref_model = tmp / "reference" / "crosscheck" / "sparse" / "0"
    scene = real_scene_from_colmap(ref_model, LUND)
    photos = tmp / "photos"  # the model knows only the photos the reference registered
    photos.mkdir()
    for name in scene.names:
        shutil.copy(LUND / name, photos / name)
    model_path = tmp / "lund_simulated.onnx"
    build_simulated_vggt(scene, model_path, NOISE)
    result = run(photos, tmp / "out", model_path, RunOptions(splat=no_splat, reference=ref_model))
    return reference, scene, model_path, result, tmp / "out"


def _median_rotation_deg(result, estimate: str) -> float:
    comparison = result.comparisons.by_label(estimate, "reference model")
    return float(np.nanmedian(comparison.per_image_rotation_deg))


def test_lund_without_a_model_is_a_usable_reference(lund_runs):
    reference, scene, *_ = lund_runs
    assert reference.exit_code == 0
    assert reference.colmap.num_registered >= 28 and len(scene) >= 28
    assert reference.colmap.mean_reprojection_error_px < 1.0


def test_lund_with_a_simulated_model_says_what_it_is(lund_runs):
    _, _, model_path, result, out = lund_runs
    meta = {p.key: p.value for p in onnx.load(str(model_path)).metadata_props}
    assert meta["ffrecon.simulated"] == "true"
    assert "COLMAP reconstruction of real photos" in json.loads(meta["ffrecon.scene"])["description"]
    assert _median_rotation_deg(result, "feed-forward") > 1.0  # the injected noise (~2.5 deg) is really there
    assert "confirmed by COLMAP" in (out / "report.html").read_text()  # the per-image evidence table


def test_lund_refined_cameras_agree_with_the_reference(lund_runs):
    """The acceptance point: refined within 0.2 deg median of the no-model reference (measured 0.08 deg,
    27 of 29 refined and confirmed by COLMAP; the last two, after the turn, take COLMAP's poses)."""
    _, scene, _, result, _ = lund_runs
    assert result.exit_code == 0
    assert result.refine.registered.sum() >= len(scene) - 3
    assert _median_rotation_deg(result, "refined") < 0.2
    assert result.evidence.count(CameraStatus.CONFIRMED) >= len(scene) - 3
    # The frames the refinement left out (after the turn) take COLMAP's poses, and the exports say where
    # every camera came from: no frame is exported at an unverified feed-forward pose.
    assert result.evidence.count(CameraStatus.CONFIRMED) + result.evidence.count(CameraStatus.COLMAP_ONLY) == len(scene)


def test_lund_thinned_to_every_4th_photo_confirms_only_what_agrees(lund_runs, tmp_path):
    """Every 4th photo (8 of 29: a sparse forward walk, about 4 steps between photos) with the model
    simulated from them: every frame carries a verdict, whatever the run calls confirmed is within 5 deg of
    the reference (issue 21), and the run ends with exit 0 either way. Measured: COLMAP registers none; 6 of
    8 are refined on SIFT and dense matches (43-95 observations each), 0.3-2.9 deg from the reference (median
    1.6; the model's 1.9), the last two stay unchecked. This test found two faults: dense evidence picked
    pairs by the smaller directed overlap (none on this forward walk), and the refined model was moved into
    the model's frame by its camera centres alone, which on a straight walk turned it 99 deg about the walk.
    """
    _, scene, _, _, _ = lund_runs
    keep = list(range(0, len(scene), 4))
    thin = dataclasses.replace(
        scene,
        names=tuple(scene.names[k] for k in keep),
        images=scene.images[keep],
        cam_from_world=scene.cam_from_world[keep],
        depth=scene.depth[keep],
    )
    photos = tmp_path / "photos"
    photos.mkdir()
    for name in thin.names:
        shutil.copy(LUND / name, photos / name)
    build_simulated_vggt(thin, tmp_path / "thin.onnx", NOISE)
    ref_model = Path(thin.options.reconstruction)
    options = RunOptions(splat=SplatOptions(enabled=False), reference=ref_model)
    result = run(photos, tmp_path / "out", tmp_path / "thin.onnx", options)
    per_image = result.evidence.per_image
    if not any(e.verdict is FrameVerdict.CONFIRMED for e in per_image):
        # Nothing checked any camera: since issue 43 (case 10) that fails the run unless forced.
        assert result.exit_code == 5, result.exit_code
        assert any(v.name == "checked_share" and v.failed for v in result.evidence.gates.verdicts)
        forced = dataclasses.replace(options, force=True)
        result = run(photos, tmp_path / "forced", tmp_path / "thin.onnx", forced)
        per_image = result.evidence.per_image
    assert result.exit_code == 0
    assert [e.name for e in per_image] == list(thin.names)
    confirmed = [k for k, e in enumerate(per_image) if e.verdict is FrameVerdict.CONFIRMED]
    if confirmed:
        errors = result.comparisons.by_label("refined", "reference model").per_image_rotation_deg
        assert np.max(np.asarray(errors)[confirmed]) < 5.0, errors
    unchecked = [e for e in per_image if e.verdict is FrameVerdict.UNCHECKED]
    assert all(e.status is CameraStatus.UNCHECKED and e.status.kept for e in unchecked)
    report = json.loads((result.out_dir / "report.json").read_text())
    assert [e["verdict"] for e in report["evidence"]["per_image"]] == [e.verdict.value for e in per_image]
