"""COLMAP cross-check, and its pose comparison checked against an independent computation."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from ffrecon.colmap_io import cam_from_world_by_name, reconstruction_from_cameras, write_reconstruction
from ffrecon.errors import InputError
from ffrecon.geometry.metrics import pose_errors
from ffrecon.sfm.compare.poses import compare_models
from ffrecon.sfm.crosscheck.mapping import drop_weak_images, map_images
from ffrecon.sfm.crosscheck.matching import resolve_camera_sharing, resolve_pairing
from ffrecon.sfm.crosscheck.options import CameraSharing, ColmapOptions, MapperKind, PairingMode
from ffrecon.sfm.crosscheck.run import ColmapStatus, run_colmap


def test_colmap_registers_the_orbit_accurately(orbit24, colmap24):
    result, out = colmap24
    assert result.status is ColmapStatus.SUCCESS
    assert result.pairing is PairingMode.EXHAUSTIVE
    assert result.num_registered == 24
    assert (out / "sparse" / "0" / "images.bin").is_file() and (out / "database.db").is_file()
    errors = pose_errors(result.cam_from_world, orbit24.scene.cam_from_world, result.registered)
    assert errors.auc[5] >= 0.98 and errors.median_rotation_deg < 0.15
    assert result.features.num_pairs_matched == 24 * 23 // 2
    assert result.features.num_keypoints.min() > 500
    assert set(result.timings.to_report()) == {"feature_extraction", "matching", "mapping", "total"}
    assert result.to_report()["registration_ratio"] == 1.0
    # AUTO mapping: incremental registered everything in one model, so the global mapper did not run.
    assert result.mapper is MapperKind.INCREMENTAL and [r.mapper for r in result.mapper_runs] == [result.mapper]
    assert result.num_models == 1 and result.mapper_runs[0].num_registered == 24
    report = result.to_report()
    assert report["mapper"] == "incremental" and report["mapper_runs"][0]["num_weak_dropped"] == 0
    # The conftest's priors differ per image (the simulated model's focal lengths): a camera each.
    assert not result.shared_camera and report["num_focal_priors"] == 24


def _independent_metrics(est: pycolmap.Reconstruction, ref: pycolmap.Reconstruction, names: list[str]) -> dict:
    """Section-5 metrics with pycolmap's own types and a plain loop (no ffrecon geometry code)."""
    by_name_est = {im.name: im for im in est.images.values()}
    by_name_ref = {im.name: im for im in ref.images.values()}
    poses_est = [by_name_est[n].cam_from_world() for n in names]
    poses_ref = [by_name_ref[n].cam_from_world() for n in names]
    rot, trans = [], []
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            rel_est = poses_est[j] * poses_est[i].inverse()
            rel_ref = poses_ref[j] * poses_ref[i].inverse()
            rot.append(np.degrees(rel_est.rotation.angle_to(rel_ref.rotation)))
            a, b = np.asarray(rel_est.translation), np.asarray(rel_ref.translation)
            trans.append(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))
    rot, trans = np.array(rot), np.array(trans)
    worst = np.maximum(rot, trans)
    out = {}
    for k in (5, 15, 30):
        out[f"RRA@{k}"] = float(np.mean(rot < k))
        out[f"RTA@{k}"] = float(np.mean(trans < k))
        out[f"AUC@{k}"] = float(np.mean([np.mean(worst < t) for t in range(1, k + 1)]))
    c_est = np.array([by_name_est[n].projection_center() for n in names])
    c_ref = np.array([by_name_ref[n].projection_center() for n in names])
    ref_from_est = pycolmap.estimate_sim3d(c_est, c_ref)
    aligned = np.array([ref_from_est.matrix() @ np.r_[c, 1.0] for c in c_est])
    out["ATE"] = float(np.sqrt(np.mean(np.sum((aligned - c_ref) ** 2, axis=1))))
    out["ATE_relative"] = out["ATE"] / float(np.linalg.norm(c_ref.max(0) - c_ref.min(0)))
    return out


def test_crosscheck_numbers_equal_an_independent_computation_from_the_written_models(orbit24, colmap24, tmp_path):
    result, out = colmap24
    names = list(orbit24.scene.names)
    ff = orbit24.prediction
    ff_dir = write_reconstruction(
        reconstruction_from_cameras(names, ff.cam_from_world, ff.cameras), tmp_path / "feedforward" / "sparse"
    )
    report = compare_models(ff_dir, out / "sparse" / "0", names, estimate="feedforward", reference="colmap").to_report()
    expected = _independent_metrics(
        pycolmap.Reconstruction(str(ff_dir)), pycolmap.Reconstruction(str(out / "sparse" / "0")), names
    )
    for key, value in expected.items():
        assert report["metrics"][key] == pytest.approx(value, rel=1e-6, abs=1e-9), key
    assert report["metrics"]["AUC@30"] > report["metrics"]["AUC@5"]  # the simulated model is off by a few degrees
    assert report["estimate"] == "feedforward" and report["reference"] == "colmap"


def test_pairing_resolution():
    assert resolve_pairing(ColmapOptions(), 20) is PairingMode.EXHAUSTIVE
    assert resolve_pairing(ColmapOptions(exhaustive_max_images=10), 20) is PairingMode.SEQUENTIAL
    assert (
        resolve_pairing(ColmapOptions(exhaustive_max_images=10, vocab_tree_path="tree.bin"), 20)
        is PairingMode.VOCAB_TREE
    )
    assert resolve_pairing(ColmapOptions(pairing=PairingMode.SEQUENTIAL), 3) is PairingMode.SEQUENTIAL


def test_camera_sharing_resolution():
    size = [(640, 480)] * 3
    assert resolve_camera_sharing(CameraSharing.AUTO, size, [None] * 3)  # one size, nothing known: one camera
    assert resolve_camera_sharing(CameraSharing.AUTO, size, [500.0, 500.0, 500.2])  # one lens setting
    assert not resolve_camera_sharing(CameraSharing.AUTO, size, [500.0, 500.0, 520.0])  # a zoom changed
    assert not resolve_camera_sharing(CameraSharing.AUTO, size, [500.0, None, 500.0])  # mixed sources
    assert not resolve_camera_sharing(CameraSharing.AUTO, [(640, 480), (480, 640), (640, 480)], [None] * 3)
    assert not resolve_camera_sharing(CameraSharing.AUTO, [(640, 480), None, (640, 480)], [None] * 3)
    assert not resolve_camera_sharing(CameraSharing.PER_IMAGE, size, [None] * 3)
    assert resolve_camera_sharing(CameraSharing.SHARED, size, [500.0, 510.0, None])
    with pytest.raises(InputError, match="one size"):
        resolve_camera_sharing(CameraSharing.SHARED, [(640, 480), (480, 640)], [None] * 2)


def test_dropping_weak_images_deregisters_them_and_their_points(colmap24):
    rec = pycolmap.Reconstruction(colmap24[0].reconstruction)
    fewest = min(image.num_points3D for image in rec.images.values())
    assert drop_weak_images(rec, fewest) == 0 and rec.num_reg_images() == 24
    assert drop_weak_images(rec, 10**9) == 24 and rec.num_reg_images() == 0 and rec.num_points3D() == 0


def test_sequential_loop_detection_needs_a_vocabulary_tree(orbit24, tmp_path):
    options = ColmapOptions(pairing=PairingMode.SEQUENTIAL, vocab_tree_path=tmp_path / "missing_tree.bin")
    with pytest.raises(InputError, match="loop detection needs a vocabulary tree"):
        run_colmap(orbit24.image_dir, orbit24.scene.names[:3], options, tmp_path, focal_prior_px=None)


def test_two_images_need_a_focal_prior(orbit24, tmp_path):
    """Two images form an uncalibrated pair: without a focal prior COLMAP keeps its guess (1.2 x width)
    and gets the relative rotation wrong; the feed-forward focal as a prior fixes that."""
    names = list(orbit24.scene.names[:2])
    truth = orbit24.scene.cam_from_world[:2]
    with_prior = run_colmap(
        orbit24.image_dir, names, ColmapOptions(), tmp_path / "prior", focal_prior_px=orbit24.prediction.cameras[0].fx
    )
    assert with_prior.num_registered == 2
    assert pose_errors(with_prior.cam_from_world, truth, with_prior.registered).rra[5] == 1.0
    assert abs(with_prior.cameras[0].fx / orbit24.scene.camera.fx - 1) < 0.05
    without = run_colmap(orbit24.image_dir, names, ColmapOptions(), tmp_path / "none", focal_prior_px=None)
    assert pose_errors(without.cam_from_world, truth, without.registered).rra[5] == 0.0


def test_sequential_pairing_and_global_mapper(orbit24, tmp_path):
    names = list(orbit24.scene.names[:8])
    options = ColmapOptions(pairing=PairingMode.SEQUENTIAL, sequential_overlap=3, mapper=MapperKind.GLOBAL)
    result = run_colmap(orbit24.image_dir, names, options, tmp_path, focal_prior_px=orbit24.scene.camera.fx)
    assert result.pairing is PairingMode.SEQUENTIAL and result.mapper is MapperKind.GLOBAL
    assert [run.mapper for run in result.mapper_runs] == [MapperKind.GLOBAL] and result.shared_camera
    assert result.features.num_pairs_matched < 8 * 7 // 2
    assert result.num_registered == 8
    poses, registered = cam_from_world_by_name(pycolmap.Reconstruction(str(tmp_path / "sparse" / "0")), names)
    errors = pose_errors(poses, orbit24.scene.cam_from_world[:8], registered)
    assert errors.median_rotation_deg < 0.5
    # The global mapper writes to the database it is given; the refinement reads this one beside the mapping
    # (a write there failed its open, "database is locked"), so the mapper gets a copy and this one stays as it was.
    database = result.database_path
    before = database.read_bytes()
    kept, _, _ = map_images(database, orbit24.image_dir, tmp_path / "again", options, len(names))
    assert kept is not None and kept.num_reg_images() == 8
    assert database.read_bytes() == before
