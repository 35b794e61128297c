"""The COLMAP cross-check on real phone photos: 29 views walking forward along two streets in Lund.

Forward motion gives small triangulation angles, the hard case for incremental SfM: on these photos
COLMAP's incremental mapper registers 2 or 3 images, and the cross-check has to fall back on the
global mapper. The photos carry EXIF (a 35 mm-equivalent focal length) and GPS positions good to
about 5 m, against which the camera centres are checked.
"""

from __future__ import annotations

import dataclasses
import json
import pickle
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from PIL import Image

from ffrecon.capture.images import focal_prior_px, read_exif
from ffrecon.geometry.alignment import umeyama
from ffrecon.sfm.crosscheck.options import ColmapOptions, MapperKind, PairingMode
from ffrecon.sfm.crosscheck.run import ColmapResult, ColmapStatus, run_colmap

LUND = Path(__file__).resolve().parents[3] / "shared" / "data" / "lund"
LONG_SIDE_PX = 640  # the photos are 1024 x 768; at 640 px one cross-check takes about 25 s on 2 cores
_GPS_IFD = 0x8825
_EARTH_RADIUS_M = 6_371_000.0

pytestmark = [
    pytest.mark.slow,  # about 35 s on 2 cores
    pytest.mark.skipif(
        len(list(LUND.glob("*.jpg"))) < 29, reason=f"the real capture (29 photos of Lund) is not at {LUND}"
    ),
]


@dataclasses.dataclass(frozen=True)
class Photos:
    image_dir: Path  # the photos at LONG_SIDE_PX, re-saved without EXIF
    names: tuple[str, ...]
    focal_prior_px: tuple[float | None, ...]  # from the originals' EXIF, in pixels of the small images


@pytest.fixture(scope="module")
def lund(tmp_path_factory) -> Photos:
    """The photos downscaled with INTER_AREA; a cv2 re-save drops EXIF, so the priors come from the originals."""
    out = tmp_path_factory.mktemp("lund")
    names, priors = [], []
    for path in sorted(LUND.glob("*.jpg")):
        bgr = cv2.imread(str(path))
        scale = LONG_SIDE_PX / max(bgr.shape[:2])
        size_wh = (round(bgr.shape[1] * scale), round(bgr.shape[0] * scale))
        cv2.imwrite(str(out / path.name), cv2.resize(bgr, size_wh, interpolation=cv2.INTER_AREA))
        _, focal_35mm, focal_px = read_exif(path)
        priors.append(focal_prior_px(*size_wh, focal_35mm, None if focal_px is None else focal_px * scale))
        names.append(path.name)
    return Photos(out, tuple(names), tuple(priors))


@pytest.fixture(scope="module")
def lund_colmap(lund, tmp_path_factory) -> ColmapResult:
    out = tmp_path_factory.mktemp("lund_colmap")
    return run_colmap(lund.image_dir, lund.names, ColmapOptions(), out, focal_prior_px=list(lund.focal_prior_px))


def _gps_east_north_m(paths: list[Path]) -> np.ndarray:
    """``[N, 3]`` EXIF GPS positions in metres (east, north, 0) about their mean; flat earth over 200 m."""
    lat_lon = []
    for path in paths:
        with Image.open(path) as img:
            gps = img.getexif().get_ifd(_GPS_IFD)
        degrees = [sum(float(v) / 60**k for k, v in enumerate(gps[tag])) for tag in (2, 4)]
        signs = [-1.0 if gps.get(1) == "S" else 1.0, -1.0 if gps.get(3) == "W" else 1.0]
        lat_lon.append([d * s for d, s in zip(degrees, signs)])
    rad = np.radians(np.array(lat_lon))
    rad -= rad.mean(0)
    north = rad[:, 0] * _EARTH_RADIUS_M
    east = rad[:, 1] * _EARTH_RADIUS_M * np.cos(np.radians(np.array(lat_lon)[:, 0].mean()))
    return np.stack([east, north, np.zeros_like(east)], axis=1)


def test_forward_walk_registers_in_one_model_with_the_global_fallback(lund, lund_colmap):
    result = lund_colmap
    assert result.status is ColmapStatus.SUCCESS and result.pairing is PairingMode.EXHAUSTIVE
    assert result.num_registered >= 28, result.to_report()["mapper_runs"]
    assert result.mean_reprojection_error_px < 1.0
    assert result.num_points > 500
    first = result.mapper_runs[0]
    assert first.mapper is MapperKind.INCREMENTAL  # AUTO tries incremental first ...
    if first.num_registered < len(lund.names):  # ... and, when it leaves images out, the global mapper too
        assert [run.mapper for run in result.mapper_runs] == [MapperKind.INCREMENTAL, MapperKind.GLOBAL]
    kept = next(run for run in result.mapper_runs if run.mapper is result.mapper)
    assert kept.num_registered == result.num_registered == max(run.num_registered for run in result.mapper_runs)
    assert result.timings.total_s < 90  # about 25 s on 2 cores


def test_one_shared_simple_radial_camera_with_the_exif_focal_as_a_prior(lund, lund_colmap):
    result = lund_colmap
    prior = lund.focal_prior_px[0]
    assert prior == pytest.approx(35 / 36 * LONG_SIDE_PX) and len(set(lund.focal_prior_px)) == 1
    assert result.shared_camera and result.focal_prior.all()
    db = pycolmap.Database.open(str(result.database_path))
    try:
        (camera,) = db.read_all_cameras()
    finally:
        db.close()
    assert camera.model.name == "SIMPLE_RADIAL" and (camera.width, camera.height) == (640, 480)
    assert camera.has_prior_focal_length and camera.focal_length == pytest.approx(prior)
    (refined,) = result.reconstruction.cameras.values()
    assert refined.model.name == "SIMPLE_RADIAL"
    assert abs(refined.focal_length / prior - 1) > 1e-3  # a prior that bundle adjustment refined, not a fixed value


def test_camera_centres_follow_the_gps_track(lund, lund_colmap):
    result = lund_colmap
    gps = _gps_east_north_m([LUND / name for name in lund.names])[result.registered]
    rotation = result.cam_from_world[result.registered, :, :3]
    centres = -np.einsum("nji,nj->ni", rotation, result.cam_from_world[result.registered, :, 3])
    fit = umeyama(centres, gps)
    rmse = float(np.sqrt(np.mean(np.sum((fit.apply(centres) - gps) ** 2, axis=1))))
    extent = float(np.linalg.norm(np.ptp(gps, axis=0)))
    assert extent > 150  # the walk spans about 180 m
    assert rmse < 10  # 4.7 m measured; the phone reports 5 m GPS accuracy


def test_the_result_pickles_without_its_reconstruction_and_reports_as_json(lund_colmap):
    result = lund_colmap
    report = json.loads(json.dumps(result.to_report()))
    assert report["mapper"] == result.mapper.value and report["shared_camera"] is True
    assert report["num_focal_priors"] == len(result.names)
    assert [run["mapper"] for run in report["mapper_runs"]] == [run.mapper.value for run in result.mapper_runs]
    back = pickle.loads(pickle.dumps(dataclasses.replace(result, reconstruction=None)))
    assert back.mapper is result.mapper and back.mapper_runs == result.mapper_runs
    assert back.names == result.names and np.array_equal(back.registered, result.registered)
    assert np.array_equal(back.cam_from_world, result.cam_from_world) and back.to_report() == result.to_report()


def test_sequential_pairing_also_registers_the_forward_walk(lund, tmp_path):
    options = ColmapOptions(pairing=PairingMode.SEQUENTIAL)
    result = run_colmap(lund.image_dir, lund.names, options, tmp_path, focal_prior_px=list(lund.focal_prior_px))
    assert result.pairing is PairingMode.SEQUENTIAL
    assert result.features.num_pairs_matched < len(lund.names) * (len(lund.names) - 1) // 2
    # 29 registered in each of 29 runs here, 25 of them with both cores kept busy; 27 once in a CI run.
    # COLMAP's CPU matching is not bit-repeatable under load: in one of those 25 runs the matches
    # differed (same keypoints and descriptors, seeded RANSAC), and the global mapper that places this
    # walk depends on them; the test allows for that one image.
    assert result.num_registered >= 27 and result.mean_reprojection_error_px < 1.0
