"""Known intrinsics in (``--intrinsics``): the model's focal is 5 % off the truth, the user gives the truth.

Fixed, the final cameras keep the given focal (within 0.1 %) and the report shows the model's own estimate
beside it; the file's format (COLMAP's cameras.txt) is parsed strictly, with errors that name the line.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pycolmap
import pytest

from ffrecon.capture import CaptureOptions
from ffrecon.errors import InputError
from ffrecon.formats.intrinsics import read_intrinsics
from ffrecon.pipeline import RunOptions, run
from ffrecon.splat.stage import SplatOptions
from ffrecon.types import PinholeCamera

FOCAL_ERROR = 0.05  # the simulated model's focal error (one signed value, plus 20 % of it per frame)


@pytest.fixture(scope="module")
def focal_off(demo_cache):
    """12 frames at 320x240 and a simulated model whose focal lengths are about 5 % off the truth."""
    from ffrecon.demo import DemoOptions, prepare_demo
    from ffrecon.synthetic import SceneOptions, load_scene

    os.environ["FFRECON_CACHE"] = str(demo_cache)
    scene = SceneOptions(num_frames=12, width=320, height=240, seed=1)
    inputs = prepare_demo(DemoOptions(scene=scene, simulation={"focal_error": FOCAL_ERROR}))
    return inputs, load_scene(inputs.scene_dir).camera


def test_fixed_intrinsics_stay_and_the_model_estimate_is_reported(focal_off, tmp_path):
    inputs, truth = focal_off
    given = tmp_path / "cameras.txt"
    given.write_text(f"# the true camera\n1 PINHOLE 320 240 {truth.fx} {truth.fy} {truth.cx} {truth.cy}\n")
    capture = CaptureOptions(intrinsics=given)
    options = RunOptions(capture=capture, splat=SplatOptions(enabled=False), ground_truth=inputs.scene_dir)
    result = run(inputs.images, tmp_path / "out", inputs.model, options)
    assert result.exit_code == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())["intrinsics"]
    assert report["fixed"] and report["given_focal_px"] == pytest.approx(truth.fx)
    assert abs(report["model"]["vs_given"]) > 0.6 * FOCAL_ERROR  # the model's own estimate, about 5 % off
    assert abs(report["final"]["vs_given"]) < 1e-3
    final = pycolmap.Reconstruction(str(tmp_path / "out" / "sparse" / "0"))
    for camera in final.cameras.values():  # every final camera: the given focal within 0.1 %
        assert camera.focal_length_x == pytest.approx(truth.fx, rel=1e-3)
        assert camera.focal_length_y == pytest.approx(truth.fy, rel=1e-3)
    transforms = json.loads((tmp_path / "out" / "transforms.json").read_text())
    assert transforms["fl_x"] == pytest.approx(truth.fx, rel=1e-3)
    assert "own estimate" in (tmp_path / "out" / "report.html").read_text()  # beside the given focal
    # The refined poses are still right: the given focal did not bend them.
    assert result.comparisons.by_label("refined", "ground truth").errors.median_rotation_deg < 0.2


def test_per_image_intrinsics_scale_to_the_frames(tmp_path):
    path = tmp_path / "cameras.txt"
    path.write_text("a.png SIMPLE_PINHOLE 640 480 500 320 240\nb.png PINHOLE 640 480 510 505 321 239\n")
    known = read_intrinsics(path)
    assert known.camera("a.png", (640, 480)) == PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)
    half = known.camera("b.png", (320, 240))
    assert (half.width, half.height) == (320, 240) and np.isclose(half.fx, 255.0) and np.isclose(half.cx, 160.5)
    with pytest.raises(InputError, match="no camera for c.png"):
        known.camera("c.png", (640, 480))
    with pytest.raises(InputError, match="another shape"):
        known.camera("a.png", (480, 480))


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("", "is empty"),
        ("# only a comment\n", "holds no camera"),
        ("1 SIMPLE_RADIAL 640 480 500 320 240\n", "takes 4 parameters"),
        ("1 FISHEYE_X 640 480 500 320 240\n", "not one ffrecon takes"),
        ("1 PINHOLE 640 480 500 320 240\n", "takes 4 parameters"),
        ("1 PINHOLE 640 480 500 500 320 240\n2 PINHOLE 640 480 500 500 320 240\n", "which photo has which"),
        ("1 PINHOLE 640 480 -500 500 320 240\n", "not a positive"),
        ("1 PINHOLE x 480 500 500 320 240\n", "must be numbers"),
    ],
)
def test_bad_intrinsics_files_say_what_is_wrong(tmp_path, text, says):
    path = tmp_path / "cameras.txt"
    path.write_text(text)
    with pytest.raises(InputError, match=says):
        read_intrinsics(path)


def test_intrinsics_as_priors_are_refined_from_the_given_values(focal_off, tmp_path):
    inputs, truth = focal_off
    given = tmp_path / "cameras.txt"
    given.write_text(f"1 SIMPLE_PINHOLE 320 240 {truth.fx * 1.01} {truth.cx} {truth.cy}\n")  # 1 % off the truth
    capture = CaptureOptions(intrinsics=given, intrinsics_prior=True)
    result = run(
        inputs.images, tmp_path / "out", inputs.model, RunOptions(capture=capture, splat=SplatOptions(enabled=False))
    )
    assert result.exit_code == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())["intrinsics"]
    assert not report["fixed"]
    final = report["final"]["focal_px"]
    assert final != pytest.approx(truth.fx * 1.01, rel=1e-4)  # the adjustment moved it ...
    assert final == pytest.approx(truth.fx, rel=0.01)  # ... towards the truth (a 1 % start, within 1 % of the truth)
