"""run_splat end to end on a tiny scene: files written, report section, validation."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from ffrecon.errors import InputError
from ffrecon.export.splat_ply import read_splat_ply
from ffrecon.splat.render_gsplat import gsplat_available
from ffrecon.splat.stage import (
    SplatDevice,
    SplatOptions,
    resolve_device,
    run_splat,
    split_views,
)
from ffrecon.synthetic import SceneOptions, make_scene


@pytest.fixture(scope="module")
def tiny():
    scene = make_scene(SceneOptions(num_frames=9, width=64, height=48))
    train, _ = split_views(len(scene), 8)
    xyz = np.concatenate([scene.frame_points(i).reshape(-1, 3) for i in train])
    rgb = np.concatenate([scene.images[i].reshape(-1, 3) for i in train]).astype(np.float32) / 255.0
    return scene, xyz, rgb


def test_run_splat_writes_everything(tiny, tmp_path):
    scene, xyz, rgb = tiny
    options = SplatOptions(
        iterations=120,
        max_seconds=60,
        max_seed_points=4000,
        video_frames=6,
        mesh=True,
        progress=False,
        device="cpu",
        sh_degree=1,
    )
    result = run_splat(
        list(scene.images), scene.names, scene.cam_from_world, [scene.camera] * len(scene), xyz, rgb, options, tmp_path
    )
    assert [v.name for v in result.heldout] == ["frame_000.png", "frame_008.png"]
    assert result.iterations == 120 and result.backend == "cpu"
    assert result.mean("psnr_optimized") > result.mean("psnr_seed") + 2.0
    assert result.count_seed <= 4000 and result.count_cleaned <= result.count_optimized
    assert len(read_splat_ply(result.ply_path)) == result.count_cleaned
    report = json.loads(json.dumps(result.to_report()))  # JSON-serialisable
    assert report["splat_ply"] == "splat.ply" and report["video"] == "flythrough.mp4"
    assert report["mesh"] == {"ply": "mesh.ply", "glb": "mesh.glb"}
    assert report["renders"][0] == {
        "view": "frame_000.png",
        "truth": "renders/frame_000_truth.png",
        "seed": "renders/frame_000_seed.png",
        "splat": "renders/frame_000_splat.png",
    }
    assert all((tmp_path / r[k]).is_file() for r in report["renders"] for k in ("truth", "seed", "splat"))
    assert len(result.report_images()) == 6
    assert len(trimesh.load(tmp_path / "mesh.glb", force="mesh").faces) > 100
    assert set(result.timings) >= {"seed", "optimize", "clean", "evaluate", "write_ply", "video", "mesh", "total"}


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
        iterations=10,
        max_seed_points=2000,
        video=False,
        refine_poses=True,
        progress=False,
        device="cpu",
        sh_degree=0,
        report_views=0,
    )
    result = run_splat(
        list(scene.images), scene.names, scene.cam_from_world, [scene.camera] * len(scene), xyz, rgb, options, tmp_path
    )
    assert result.cam_from_world.shape == (9, 3, 4) and result.render_paths == () and result.video_path is None
    assert np.array_equal(result.cam_from_world[1], scene.cam_from_world[1])  # first training view: gauge
    assert np.array_equal(result.cam_from_world[0], scene.cam_from_world[0])  # held out: not refined
    assert not np.array_equal(result.cam_from_world[2], scene.cam_from_world[2])
