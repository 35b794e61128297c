"""No model: photos -> COLMAP -> gates -> splat seeded from COLMAP's points -> exports and report."""

import json

import numpy as np
import pycolmap

from ffrecon.cli import main
from ffrecon.geometry.alignment import umeyama
from ffrecon.geometry.poses import camera_centers
from ffrecon.pipeline import RunOptions, run
from ffrecon.results import Skipped
from ffrecon.splat.optimize import OptimizeOptions
from ffrecon.splat.stage import SplatOptions
from ffrecon.synthetic import SceneOptions, make_scene, write_scene
from ffrecon.synthetic.simulated_model import SimulationOptions, build_simulated_vggt


def test_no_model_reconstructs_from_colmap_alone(demo12, tmp_path):
    out = tmp_path / "out"
    splat = SplatOptions(optimize=OptimizeOptions.brief(iterations=30, max_seconds=1e6, progress=False), video=False)
    result = run(demo12.images, out, None, RunOptions(splat=splat, ground_truth=demo12.scene_dir))
    rec = pycolmap.Reconstruction(str(out / "crosscheck" / "sparse" / "0"))
    assert result.exit_code == 0
    assert isinstance(result.feedforward, Skipped) and "--model" in result.feedforward.reason
    assert isinstance(result.refine, Skipped)
    assert result.colmap.num_registered == 12
    # COLMAP's cameras are the final ones (no focal prior: the PNGs carry no EXIF): within 0.25 deg of truth.
    errors = result.comparisons.by_label("COLMAP", "ground truth").errors
    assert errors.median_rotation_deg < 0.25 and errors.auc[5] > 0.9
    # The splat is seeded from COLMAP's points and measured on held-out views it never saw.
    assert result.splat.count_seed <= result.colmap.num_points and result.splat.heldout == (0, 8)
    assert result.splat.mean("psnr_cleaned") > result.splat.mean("psnr_seed") + 1.0
    # Exports use COLMAP's cameras and points; nerfstudio's file lists the registered frames.
    assert result.exports.cameras_from == "COLMAP" and "COLMAP" in result.exports.points_from
    transforms = json.loads((out / "transforms.json").read_text())
    assert len(transforms["frames"]) == 12
    # COLMAP's SIMPLE_RADIAL camera: transforms.json says OPENCV with its k1 (the splat trained undistorted).
    k1 = rec.cameras[1].params[3]
    assert transforms["camera_model"] == "OPENCV" and transforms["k1"] == k1 and transforms["k2"] == 0.0
    assert result.exports.num_points == rec.num_points3D()
    # sparse/0 holds the final cameras, COLMAP's here: the same model as crosscheck/sparse/0 (docs/contracts.md);
    # colmap/sparse/0, where nerfstudio's COLMAP parser looks, is a copy of sparse/0.
    final = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert final.num_reg_images() == 12 and final.num_points3D() == rec.num_points3D()
    for image in final.images.values():
        same = rec.images[image.image_id]
        assert same.name == image.name and np.allclose(same.cam_from_world().matrix(), image.cam_from_world().matrix())
    copy = pycolmap.Reconstruction(str(out / "colmap" / "sparse" / "0"))
    assert {i.name: i.cam_from_world().matrix().tolist() for i in copy.images.values()} == {
        i.name: i.cam_from_world().matrix().tolist() for i in final.images.values()
    }
    report = json.loads((out / "report.json").read_text())
    assert report["feedforward"] == {"skipped": result.feedforward.reason}
    assert "none: cameras from COLMAP" in (out / "report.html").read_text()


def test_no_model_and_no_colmap_is_refused(demo12, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["run", str(demo12.images), "-o", str(out), "--no-colmap", "-q"]) == 2
    assert "--model" in capsys.readouterr().err
    assert not out.exists()
    one = tmp_path / "one"
    one.mkdir()
    (one / "a.png").write_bytes(next(iter(sorted(demo12.images.iterdir()))).read_bytes())
    assert main(["run", str(one), "-o", str(out), "-q"]) == 2


def test_unsuited_model_is_set_aside_for_colmaps_cameras(tmp_path):
    """A model wrong on most frames, against a healthy COLMAP model: the run goes on from COLMAP's cameras."""
    scene = make_scene(SceneOptions(num_frames=12, width=320, height=240, seed=1))
    images = write_scene(scene, tmp_path / "scene")
    bad = SimulationOptions(bad_frames=tuple(range(1, 12)), bad_rotation_deg=25.0, seed=1)
    build_simulated_vggt(scene, tmp_path / "bad.onnx", bad)
    splat = SplatOptions(optimize=OptimizeOptions.brief(iterations=10, max_seconds=1e6, progress=False), video=False)
    options = RunOptions(splat=splat, ground_truth=tmp_path / "scene")
    result = run(images, tmp_path / "out", tmp_path / "bad.onnx", options)
    assert result.exit_code == 0
    assert result.evidence.model_unsuited and "COLMAP's cameras are used" in result.evidence.unsuited_reason
    assert result.exports.cameras_from == "COLMAP" and "COLMAP" in result.exports.points_from
    assert not isinstance(result.splat, Skipped)
    # The exported cameras are COLMAP's, which are right, unlike the model's.
    errors = result.comparisons.by_label("COLMAP", "ground truth").errors
    assert errors.median_rotation_deg < 0.25
    assert result.comparisons.by_label("feed-forward", "ground truth").errors.median_rotation_deg > 10


def test_compare_seeds_trains_both_under_one_budget(demo12, tmp_path):
    """--compare-seeds: the feed-forward-seeded splat against one seeded from COLMAP's points."""
    brief = OptimizeOptions.brief(iterations=40, max_seconds=1e6, progress=False)
    splat = SplatOptions(optimize=brief, video=False, compare_seeds=True)
    out = tmp_path / "out"
    result = run(demo12.images, out, demo12.model, RunOptions(splat=splat))
    ff, sfm = result.splat, result.seed_comparison
    assert ff.iterations == sfm.iterations == 40 and ff.heldout == sfm.heldout
    assert [c[0] for c in ff.heldout_curve] == [c[0] for c in sfm.heldout_curve] == [0, 20, 40]
    assert sfm.count_seed == min(result.colmap.num_points, splat.max_seed_points)
    # COLMAP's points were moved into the final cameras' frame: the SfM seed already renders the views.
    # COLMAP's points moved into the final cameras' frame: they project into the views (an independent
    # Umeyama fit on the camera centres), and the SfM-seeded splat renders far better than black.
    final, colmap = result.refine, result.colmap
    to_final = umeyama(camera_centers(colmap.cam_from_world), camera_centers(final.cam_from_world))
    xyz = to_final.apply(np.array([p.xyz for p in colmap.reconstruction.points3D.values()]))
    cam = final.cameras[1]
    local = xyz @ final.cam_from_world[1][:, :3].T + final.cam_from_world[1][:, 3]
    u = cam.fx * local[:, 0] / local[:, 2] + cam.cx
    inside = (local[:, 2] > 0) & (u > 0) & (u < cam.width)
    assert inside.mean() > 0.3
    black = np.mean([10 * np.log10(1 / np.mean((im / 255.0) ** 2)) for im in result.capture.read_images([0, 8])])
    assert sfm.mean("psnr_cleaned") > black + 2 and ff.mean("psnr_cleaned") > sfm.mean("psnr_cleaned")
    page = (out / "report.html").read_text()
    assert "Seeds compared" in page and "Held-out quality over time" in page
    assert (out / "seed_comparison" / "splat.ply").is_file()
