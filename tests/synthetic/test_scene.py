"""Synthetic scenes: exact depth (pixel-centre rule), consistency across views, I/O, texture options."""

import dataclasses

import numpy as np
import pycolmap
import pytest

from ffrecon.geometry.metrics import pose_errors
from ffrecon.geometry.poses import camera_centers
from ffrecon.geometry.projection import project_points
from ffrecon.synthetic import CameraPath, SceneOptions, Texture, load_scene, make_scene, render, write_scene
from ffrecon.synthetic.scene import ROOM_HI, ROOM_LO, _surface_textures, scene_geometry

SMALL = SceneOptions(num_frames=6, width=160, height=120, seed=4)


@pytest.fixture(scope="module")
def small():
    return make_scene(SMALL)


def _gradient_energy(images: np.ndarray) -> np.ndarray:
    """Mean absolute horizontal + vertical difference per image, in grey levels."""
    grey = images.astype(np.float64).mean(-1)
    return np.abs(np.diff(grey, axis=1)).mean((1, 2)) + np.abs(np.diff(grey, axis=2)).mean((1, 2))


def test_shapes_intrinsics_and_determinism(small):
    n, h, w = SMALL.num_frames, SMALL.height, SMALL.width
    assert small.images.shape == (n, h, w, 3) and small.images.dtype == np.uint8
    assert small.depth.shape == (n, h, w) and small.depth.dtype == np.float32
    assert small.cam_from_world.shape == (n, 3, 4) and small.names[2] == "frame_002.png"
    assert (small.camera.cx, small.camera.cy) == (w / 2, h / 2)
    assert small.camera.fov_deg()[0] == pytest.approx(SMALL.fov_x_deg, abs=1e-9)
    rot = small.cam_from_world[:, :, :3]
    np.testing.assert_allclose(rot @ np.swapaxes(rot, 1, 2), np.broadcast_to(np.eye(3), rot.shape), atol=1e-12)
    assert np.all(np.isfinite(small.depth)) and small.depth.min() > 0.3
    # Cameras inside the room, about 1.9 units from the look-at point, textures vary.
    centers = camera_centers(small.cam_from_world)
    assert np.all((centers > ROOM_LO) & (centers < ROOM_HI))
    assert np.allclose(np.linalg.norm(centers - [0, 0, 0.55], axis=1), np.hypot(1.75, 0.8), atol=1e-9)
    again = make_scene(SMALL)
    assert np.array_equal(again.images, small.images) and np.array_equal(again.depth, small.depth)
    other = make_scene(dataclasses.replace(SMALL, seed=5))
    assert np.array_equal(other.depth, small.depth) and np.abs(other.images.astype(int) - small.images).mean() > 20


def test_depth_is_z_depth_through_pixel_centres(small):
    """Independent of the renderer: floor and wall pixels against analytic ray-plane intersections."""
    K, h, w = small.camera.K, SMALL.height, SMALL.width
    rows, cols = np.mgrid[0:h, 0:w]
    ray_cam = np.stack([(cols + 0.5 - K[0, 2]) / K[0, 0], (rows + 0.5 - K[1, 2]) / K[1, 1], np.ones((h, w))], -1)
    checked = 0
    for i in range(SMALL.num_frames):
        rot, trans = small.cam_from_world[i, :, :3], small.cam_from_world[i, :, 3]
        center = -rot.T @ trans
        ray = ray_cam @ rot  # world direction with unit camera-z component: t is z-depth
        # Which surface each pixel sees (room faces are numbered 2 * axis + side).
        surface = render.intersect(scene_geometry(), center, ray.reshape(-1, 3))[1].reshape(h, w)
        for axis, side in ((2, 0), (0, 0), (0, 1), (1, 0), (1, 1)):
            value = (ROOM_HI if side else ROOM_LO)[axis]
            on_plane = surface == 2 * axis + side
            z_analytic = (value - center[axis]) / ray[..., axis]
            np.testing.assert_allclose(small.depth[i][on_plane], z_analytic[on_plane], rtol=2e-6)
            checked += int(on_plane.sum())
    assert checked > 0.5 * small.depth.size
    # Half a pixel matters: the same test with pixel corners (no +0.5) fails on the floor.
    corner = (
        np.stack([(cols - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1], np.ones((h, w))], -1)
        @ small.cam_from_world[0, :, :3]
    )
    floor = np.abs(small.frame_points(0)[..., 2]) < 1e-4
    z_corner = -camera_centers(small.cam_from_world[:1])[0, 2] / corner[..., 2]
    assert np.median(np.abs(z_corner[floor] / small.depth[0][floor] - 1)) > 1e-3


def test_unprojected_points_land_where_other_views_see_them(small):
    geometry = scene_geometry()
    K, h, w = small.camera.K, SMALL.height, SMALL.width
    for i, j in ((0, 1), (1, 3), (4, 2)):
        pts = small.frame_points(i).reshape(-1, 3)
        uv, z = project_points(pts, K, small.cam_from_world[j])
        inside = (uv[:, 0] > 0) & (uv[:, 0] < w) & (uv[:, 1] > 0) & (uv[:, 1] < h) & (z > 0)
        # Exact: what frame j sees through that (sub-pixel) position.
        seen = render.cast_depth(geometry, small.cam_from_world[j], K, uv[inside])
        rel = (z[inside] - seen) / z[inside]
        visible = np.abs(rel) < 1e-5
        assert visible.mean() > 0.15, "neighbouring views share a good part of the scene"
        assert (rel > -1e-4).mean() > 0.999, "no point of frame i is seen behind a surface in frame j"
        # Against the stored depth of frame j: inverse depth is affine on a plane, so bilinear
        # interpolation of 1/depth at (uv - 0.5) (array coordinates, COLMAP rule) is exact there.
        origin, dirs = render.camera_rays(small.cam_from_world[j], K, h, w, np.zeros((1, 2)))
        surface = render.intersect(geometry, origin, dirs.reshape(-1, 3))[1].reshape(h, w)
        inv = 1.0 / small.depth[j].astype(np.float64)
        x, y = uv[inside][visible, 0] - 0.5, uv[inside][visible, 1] - 0.5
        x0, y0 = np.clip(np.floor(x).astype(int), 0, w - 2), np.clip(np.floor(y).astype(int), 0, h - 2)
        fx, fy = x - x0, y - y0
        quad = np.stack([inv[y0, x0], inv[y0, x0 + 1], inv[y0 + 1, x0], inv[y0 + 1, x0 + 1]])
        interp = (quad[0] * (1 - fx) + quad[1] * fx) * (1 - fy) + (quad[2] * (1 - fx) + quad[3] * fx) * fy
        ids = np.stack([surface[y0, x0], surface[y0, x0 + 1], surface[y0 + 1, x0], surface[y0 + 1, x0 + 1]])
        planar = (ids == ids[0]).all(0) & (ids[0] < len(geometry.quads))  # one flat face under all four
        err = np.abs(1.0 / interp[planar] / z[inside][visible][planar] - 1)
        assert planar.mean() > 0.5 and err.max() < 2e-5, (i, j, err.max())
        # A half-pixel slip in the convention would show: the same lookup at uv (not uv - 0.5).
        slip = inv[np.clip(y0 + 1, 0, h - 1), np.clip(x0 + 1, 0, w - 1)]  # nearest sample to uv, not uv - 0.5
        assert np.median(np.abs(1.0 / slip[planar] / z[inside][visible][planar] - 1)) > 10 * err.max()


def test_write_and_load_round_trip(small, tmp_path):
    images = write_scene(small, tmp_path / "scene")
    assert images == tmp_path / "scene" / "images" and sorted(p.name for p in images.iterdir()) == list(small.names)
    back = load_scene(tmp_path / "scene")
    assert back.options == small.options and back.names == small.names and back.camera == small.camera
    assert np.array_equal(back.images, small.images) and np.array_equal(back.depth, small.depth)
    np.testing.assert_array_equal(back.cam_from_world, small.cam_from_world)


def test_paths_textures_and_photometric_options():
    base = SceneOptions(num_frames=4, width=96, height=72, seed=2)
    arc = make_scene(dataclasses.replace(base, path=CameraPath.ARC))
    forward = make_scene(dataclasses.replace(base, path=CameraPath.FORWARD))
    rich = make_scene(base)
    # Arc spans 90 degrees around the centre; forward walks ~3 units looking the same way.
    c_arc = camera_centers(arc.cam_from_world)[:, :2]
    angle = np.degrees(np.arccos(c_arc[0] @ c_arc[-1] / np.linalg.norm(c_arc[0]) / np.linalg.norm(c_arc[-1])))
    assert angle == pytest.approx(90.0, abs=1e-6)
    assert np.linalg.norm(np.diff(camera_centers(forward.cam_from_world), axis=0), axis=1).sum() == pytest.approx(
        3.0, abs=0.05
    )
    np.testing.assert_allclose(forward.cam_from_world[0, :, :3], forward.cam_from_world[-1, :, :3], atol=1e-12)

    flat = make_scene(dataclasses.replace(base, texture=Texture.TEXTURELESS))
    assert _gradient_energy(flat.images).max() < 0.15 * _gradient_energy(rich.images).min()
    np.testing.assert_array_equal(flat.depth, rich.depth)
    some_flat = make_scene(dataclasses.replace(base, textureless_frames=(1,)))
    energy = _gradient_energy(some_flat.images)
    assert energy[1] < 0.15 * np.delete(energy, 1).min()
    assert np.array_equal(some_flat.images[0], rich.images[0])

    blurred = make_scene(dataclasses.replace(base, blur_sigma_px=2.0))
    assert np.all(_gradient_energy(blurred.images) < 0.6 * _gradient_energy(rich.images))
    drift = make_scene(dataclasses.replace(base, exposure_jitter=0.3))
    ratio = drift.images.mean((1, 2, 3)) / rich.images.mean((1, 2, 3))
    assert np.ptp(ratio) > 0.1 and np.all(np.abs(np.log(ratio)) < 1.5)

    # REPEATED: the same tile on every surface; floor points one tile (0.75 units) apart look alike.
    geometry = scene_geometry()
    textures, densities = _surface_textures(geometry, Texture.REPEATED, np.random.default_rng(0))
    floor = 4  # face 2 * axis + side: z, low side
    pts = np.array([[0.3, -2.0, 0.0], [1.05, -2.0, 0.0], [0.3, -1.25, 0.0], [0.6, -1.9, 0.0]])
    colours = render.shade(geometry, textures, pts, np.full(4, floor), texels_per_unit=densities, wrap=True)
    np.testing.assert_allclose(colours[0], colours[1], atol=1e-5)
    np.testing.assert_allclose(colours[0], colours[2], atol=1e-5)
    assert np.abs(colours[0] - colours[3]).max() > 1e-3


def test_invalid_options_are_rejected():
    with pytest.raises(ValueError, match="textureless_frames"):
        make_scene(SceneOptions(num_frames=3, width=32, height=24, textureless_frames=(3,)))
    with pytest.raises(ValueError, match="num_frames"):
        make_scene(SceneOptions(num_frames=0))


@pytest.mark.slow
def test_colmap_registers_every_rich_orbit_frame(tmp_path):
    """The default scene: SIFT + exhaustive matching + incremental mapping with the true focal (~15 s)."""
    scene = make_scene(SceneOptions())
    image_dir = write_scene(scene, tmp_path)
    cam = scene.camera
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = f"{cam.fx},{cam.fy},{cam.cx},{cam.cy}"
    db = tmp_path / "database.db"
    pycolmap.extract_features(
        db, image_dir, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader, device=pycolmap.Device.cpu
    )
    pycolmap.match_exhaustive(db, device=pycolmap.Device.cpu)
    options = pycolmap.IncrementalPipelineOptions()
    options.ba_refine_focal_length = False
    options.ba_refine_principal_point = False
    recs = pycolmap.incremental_mapping(db, image_dir, tmp_path / "sparse", options)
    assert len(recs) == 1
    rec = recs[0]
    by_name = {im.name: im for im in rec.images.values() if im.has_pose}
    assert sorted(by_name) == list(scene.names)
    est = np.stack([by_name[n].cam_from_world().matrix() for n in scene.names])
    errors = pose_errors(est, scene.cam_from_world)
    assert errors.median_rotation_deg < 0.3 and errors.ate_relative < 5e-3 and errors.auc[5] > 0.95
