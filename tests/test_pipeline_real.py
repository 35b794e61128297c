"""Real photos from shutter to splat, with no model: 29 phone photos walking along two streets (lund).

The photos are downscaled to keep CI short; PIL keeps their EXIF, so the focal prior comes from the
35 mm-equivalent focal length exactly as for the originals.
"""

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from ffrecon.geometry.rotations import rotation_angle_deg
from ffrecon.pipeline import RunOptions, run
from ffrecon.results import Skipped, Verdict
from ffrecon.sfm.crosscheck.options import MapperKind
from ffrecon.splat.optimize import OptimizeOptions
from ffrecon.splat.stage import SplatOptions

LUND = Path(__file__).resolve().parents[2] / "shared" / "data" / "lund"
LONG_SIDE_PX = 640  # at 512 px COLMAP keeps only 26 of 29 (weak images dropped)

pytestmark = [
    pytest.mark.slow,  # about a minute on 2 cores
    pytest.mark.skipif(len(list(LUND.glob("*.jpg"))) < 29, reason=f"the real capture is not at {LUND}"),
]


@pytest.fixture(scope="module")
def lund_small(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("lund")
    for path in sorted(LUND.glob("*.jpg")):
        with Image.open(path) as im:
            exif = im.info["exif"]
            im.thumbnail((LONG_SIDE_PX, LONG_SIDE_PX), Image.Resampling.LANCZOS)
            im.save(out / path.name, quality=95, exif=exif)
    (out / "LICENSE").write_text((LUND / "LICENSE").read_text())  # as the dataset ships
    return out


@pytest.fixture(scope="module")
def lund_run(lund_small, tmp_path_factory):
    splat = SplatOptions(optimize=OptimizeOptions.brief(iterations=40, max_seconds=1e6, progress=False), video=False)
    out = tmp_path_factory.mktemp("run") / "out"
    return run(lund_small, out, None, RunOptions(splat=splat)), out


def test_lund_without_a_model(lund_run):
    result, out = lund_run
    assert result.verdict is Verdict.OK and result.exit_code == 0
    assert isinstance(result.feedforward, Skipped)
    colmap = result.colmap
    assert colmap.num_registered >= 28 and colmap.num_models == 1
    assert colmap.mean_reprojection_error_px < 1.0
    assert all(f.focal_prior_px is not None for f in result.capture.frames)  # EXIF survived the downscale
    assert not any(v.failed for v in result.gates.verdicts)
    # A splat seeded from COLMAP's points, scored on held-out photos it never saw.
    assert len(result.splat.heldout) >= 3 and result.splat.mean("psnr_cleaned") > result.splat.mean("psnr_seed")
    transforms = json.loads((out / "transforms.json").read_text())
    assert transforms["camera_model"] == "OPENCV" and len(transforms["frames"]) == colmap.num_registered
    report = json.loads((out / "report.json").read_text())
    assert report["splat"]["heldout_mean"]["psnr_cleaned"] == pytest.approx(result.splat.mean("psnr_cleaned"))
    # Cleaning never costs the written splat more than 0.1 dB of held-out PSNR, and each step says what it did.
    assert result.splat.mean("psnr_cleaned") >= result.splat.mean("psnr_optimized") - 0.1 - 1e-9
    steps = report["splat"]["cleaning"]["steps"]
    assert [s["step"] for s in steps][:3] == ["outside_crop_box", "low_opacity", "too_large"]
    assert all("psnr_after" in s for s in steps)


def _relative(cam_from_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and unit translation of camera 1 from camera 0."""
    R = cam_from_world[1, :, :3] @ cam_from_world[0, :, :3].T
    t = cam_from_world[1, :, 3] - R @ cam_from_world[0, :, 3]
    return R, t / np.linalg.norm(t)


def test_two_photos_walking_forward_give_a_two_view_reconstruction(lund_small, lund_run, tmp_path):
    """Two consecutive photos of a forward walk: hundreds of verified matches, too little parallax for
    COLMAP's initial pair. ffrecon builds the pair itself (essential matrix with the EXIF focal length)
    and says so; its relative pose agrees with the 29-photo reconstruction's (measured: rotation 1.0 deg,
    baseline direction 0.5 deg at full size)."""
    pair = tmp_path / "pair"
    pair.mkdir()
    for name in ("01.jpg", "02.jpg"):
        (pair / name).write_bytes((lund_small / name).read_bytes())
    result = run(pair, tmp_path / "out", None, RunOptions(splat=SplatOptions(enabled=False)))
    colmap = result.colmap
    assert colmap.mapper is MapperKind.TWO_VIEW and colmap.num_registered == 2
    assert [r.mapper for r in colmap.mapper_runs][-1] is MapperKind.TWO_VIEW
    assert colmap.mapper_runs[0].num_registered < 2  # COLMAP's own mappers refused the pair
    assert int(colmap.features.num_inlier_matches.min()) > 100
    reference = lund_run[0].colmap
    ref_poses = reference.cam_from_world[[reference.names.index(n) for n in ("01.jpg", "02.jpg")]]
    (R, t), (R_ref, t_ref) = _relative(colmap.cam_from_world), _relative(ref_poses)
    assert rotation_angle_deg(R.T @ R_ref) < 2.0
    assert np.degrees(np.arccos(np.clip(t @ t_ref, -1, 1))) < 5.0  # the right baseline direction
    assert "two-view reconstruction built by ffrecon" in (tmp_path / "out" / "report.html").read_text()


def test_two_photos_without_a_focal_prior_name_small_parallax(lund_small, tmp_path):
    """Without EXIF there is no focal prior for the pair: the diagnosis names small parallax, never
    "too little overlap"."""
    pair = tmp_path / "pair"
    pair.mkdir()
    for name in ("01.jpg", "02.jpg"):
        with Image.open(lund_small / name) as im:
            im.save(pair / name, quality=95)  # no EXIF
    result = run(pair, tmp_path / "out", None, RunOptions(splat=SplatOptions(enabled=False)))
    assert result.exit_code == 5
    gate = result.gates.verdicts[0]
    assert gate.name == "registration" and gate.failed
    assert [c.value for c in gate.causes] == ["small_parallax"] and "overlap too little" not in gate.fix
    assert int(result.colmap.features.num_inlier_matches.min()) > 100
