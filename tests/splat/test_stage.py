"""run_splat and run_splat_from_prediction end to end on a tiny scene: files written, report section,
validation, one held-out split."""

from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest

from ffrecon.errors import InputError
from ffrecon.formats.splat_ply import read_splat_ply
from ffrecon.splat.clean import CleanOptions
from ffrecon.splat.optimize import OptimizeOptions
from ffrecon.splat.render_gsplat import gsplat_available
from ffrecon.splat.seed import seed_from_prediction
from ffrecon.splat.stage import (
    SplatDevice,
    SplatOptions,
    resolve_device,
    run_splat,
    run_splat_from_prediction,
)
from ffrecon.types import ModelFamily, ModelInfo, Prediction
from tests.splat.conftest import seeded_scene


@pytest.fixture(scope="module")
def tiny():
    return seeded_scene(64, 48)


def test_run_splat_writes_everything(tiny, tmp_path):
    scene, xyz, rgb = tiny
    options = SplatOptions(
        max_seed_points=4000,
        video_frames=6,
        device="cpu",
        optimize=OptimizeOptions.brief(iterations=120, max_seconds=60, progress=False, sh_degree=1),
    )
    result = run_splat(
        list(scene.images), scene.names, scene.cam_from_world, [scene.camera] * len(scene), xyz, rgb, options, tmp_path
    )
    assert [v.name for v in result.heldout_metrics] == ["frame_000.png", "frame_008.png"]
    assert result.heldout == (0, 8) and result.train == (1, 2, 3, 4, 5, 6, 7)
    assert result.iterations == 120 and result.backend == "cpu"
    assert result.mean("psnr_optimized") > result.mean("psnr_seed") + 2.0
    assert result.count_seed <= 4000 and result.count_cleaned <= result.count_optimized
    assert len(read_splat_ply(result.ply_path)) == result.count_cleaned
    report = json.loads(json.dumps(result.to_report()))  # JSON-serialisable
    assert report["splat_ply"] == "splat.ply" and report["video"] == "flythrough.mp4"
    assert report["renders"][0] == {
        "view": "frame_000.png",
        "truth": "renders/frame_000_truth.png",
        "seed": "renders/frame_000_seed.png",
        "splat": "renders/frame_000_splat.png",
    }
    assert all((tmp_path / r[k]).is_file() for r in report["renders"] for k in ("truth", "seed", "splat"))
    mean, first = report["heldout_mean"], report["heldout_per_view"][0]
    assert set(mean) == set(first) - {"name"} >= {"psnr_cleaned_color_corrected", "ssim_cleaned_color_corrected"}
    # A least-squares colour fit cannot make the render worse (up to the light ridge and clipping).
    assert mean["psnr_cleaned_color_corrected"] >= mean["psnr_cleaned"] - 0.05
    assert result.color_transforms.shape == (9, 3, 4) and np.allclose(result.color_transforms[[0, 8]], np.eye(3, 4))
    assert len(result.report_images()) == 6
    assert set(result.timings.to_report()) >= {"seed", "optimize", "clean", "evaluate", "write_ply", "video", "total"}
    assert not (tmp_path / "mesh.ply").exists()  # the mesh belongs to the export stage


def test_validation_and_devices(tiny, tmp_path):
    scene, xyz, rgb = tiny
    with pytest.raises(InputError):
        run_splat(
            list(scene.images)[:3],
            scene.names,
            scene.cam_from_world,
            [scene.camera] * len(scene),
            xyz,
            rgb,
            SplatOptions(),
            tmp_path,
        )
    with pytest.raises(ValueError):
        run_splat(
            list(scene.images),
            scene.names,
            scene.cam_from_world,
            [scene.camera] * len(scene),
            xyz,
            rgb[:10],
            SplatOptions(),
            tmp_path,
        )
    assert resolve_device(SplatDevice.CPU) == "cpu"
    assert resolve_device("auto") == ("cuda" if gsplat_available() else "cpu")
    if not gsplat_available():
        with pytest.raises(InputError):
            resolve_device("cuda")


def test_refine_poses_runs_and_keeps_the_gauge_camera(tiny, tmp_path):
    scene, xyz, rgb = tiny
    options = SplatOptions(
        max_seed_points=2000,
        video=False,
        device="cpu",
        report_views=0,
        optimize=OptimizeOptions.brief(iterations=10, refine_poses=True, progress=False, sh_degree=0),
    )
    result = run_splat(
        list(scene.images), scene.names, scene.cam_from_world, [scene.camera] * len(scene), xyz, rgb, options, tmp_path
    )
    assert result.cam_from_world.shape == (9, 3, 4) and result.render_paths == () and result.video_path is None
    assert np.array_equal(result.cam_from_world[1], scene.cam_from_world[1])  # first training view: gauge
    assert np.array_equal(result.cam_from_world[0], scene.cam_from_world[0])  # held out: not refined
    assert not np.array_equal(result.cam_from_world[2], scene.cam_from_world[2])


def test_defaults_are_the_brief_optimiser_and_nothing_is_repeated():
    options = SplatOptions()
    assert options.optimize == OptimizeOptions.brief()
    assert (options.optimize.iterations, options.optimize.max_seconds, options.optimize.sh_degree) == (1500, 60.0, 3)
    assert (
        options.optimize.resolution_schedule == ((0.0, 4), (0.1, 2), (0.3, 1)) and options.optimize.plateau_window > 0
    )
    assert (options.holdout_every, options.max_seed_points, options.optimize.max_gaussians) == (8, 60_000, 100_000)
    own = {f.name for f in dataclasses.fields(SplatOptions)}
    assert not own & {f.name for f in dataclasses.fields(OptimizeOptions)} - {"device"}
    assert not own & {f.name for f in dataclasses.fields(CleanOptions)}


def _prediction(scene, depth_scale: float) -> Prediction:
    """The scene's true depth as a feed-forward prediction, stored on a grid ``depth_scale`` times the photo's."""
    size = (round(scene.camera.width * depth_scale), round(scene.camera.height * depth_scale))
    depth = tuple(cv2.resize(d, size, interpolation=cv2.INTER_NEAREST) for d in scene.depth)
    return Prediction(
        names=tuple(scene.names),
        cam_from_world=np.asarray(scene.cam_from_world, np.float64),
        cameras=(scene.camera,) * len(scene),
        depth=depth,
        depth_conf=tuple(np.full_like(d, 2.0) for d in depth),
        model=ModelInfo(path="truth", family=ModelFamily.MULTIVIEW, simulated=True),
    )


@pytest.mark.parametrize("depth_scale", [1.0, 0.5])
def test_from_prediction_seeds_from_the_training_views_only(tiny, tmp_path, depth_scale):
    scene, _, _ = tiny
    prediction = _prediction(scene, depth_scale)
    options = SplatOptions(
        max_seed_points=3000,
        video=False,
        device="cpu",
        report_views=1,
        optimize=OptimizeOptions.brief(iterations=20, max_seconds=1e9, progress=False, sh_degree=1, threads=1),
    )
    images = list(scene.images)
    cameras = [scene.camera] * len(scene)
    result = run_splat_from_prediction(prediction, images, scene.cam_from_world, cameras, options, tmp_path / "a")
    assert result.heldout == (0, 8) and result.train == (1, 2, 3, 4, 5, 6, 7)
    assert result.timings.seconds("fuse_depth") > 0

    # The same run by hand: seed from the training views' depth (images resized to it), then run_splat.
    small = [cv2.resize(im, d.shape[::-1], interpolation=cv2.INTER_AREA) for im, d in zip(images, prediction.depth)]
    xyz, rgb = seed_from_prediction(prediction, small, max_points=3000, frames=list(result.train), seed=0)
    by_hand = run_splat(images, scene.names, scene.cam_from_world, cameras, xyz, rgb, options, tmp_path / "b")
    assert result.heldout_metrics == by_hand.heldout_metrics
    assert result.ply_path.read_bytes() == by_hand.ply_path.read_bytes()

    # A held-out frame's depth does not reach the seed: changing it changes nothing.
    depth = list(prediction.depth)
    depth[8] = depth[8] * 1.5
    changed = dataclasses.replace(prediction, depth=tuple(depth))
    again = run_splat_from_prediction(changed, images, scene.cam_from_world, cameras, options, tmp_path / "c")
    assert again.ply_path.read_bytes() == result.ply_path.read_bytes()
