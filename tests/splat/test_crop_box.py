"""A crop box given by hand: six numbers or a small JSON file, read, checked, and applied to the splat."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ffrecon.errors import InputError
from ffrecon.splat.clean import (
    CROP_BOX_FRAME,
    CleanOptions,
    clean_gaussians,
    crop_box_from_args,
    read_crop_box,
    write_crop_box,
)
from tests.splat.test_clean import _scene


def test_a_box_file_round_trips_and_crops_like_the_numbers(tmp_path):
    box = ((-0.6, -0.6, 0.0), (0.6, 0.6, 0.6))
    file = write_crop_box(tmp_path / "box.json", box)
    assert json.loads(file.read_text()) == {"frame": CROP_BOX_FRAME, "lo": [-0.6, -0.6, 0.0], "hi": [0.6, 0.6, 0.6]}
    assert read_crop_box(file) == box == crop_box_from_args([str(file)])
    assert crop_box_from_args(["-0.6", "-0.6", "0", "0.6", "0.6", "0.6"]) == box
    g, poses, cams = _scene(np.random.default_rng(1))
    out, report = clean_gaussians(g, poses, cams, CleanOptions(crop_box=read_crop_box(file), floater_std_ratio=0))
    kept = out.means.numpy()
    assert np.all(kept >= np.array(box[0]) - 1e-6) and np.all(kept <= np.array(box[1]) + 1e-6)
    assert len(out) == np.sum(g.means.numpy()[:6000, 2] >= 0)  # the cube's upper half, nothing else
    assert report.to_dict()["crop_box"] == {
        "frame": "sparse/0",
        "lo": [-0.6, -0.6, 0.0],
        "hi": [0.6, 0.6, 0.6],
        "automatic": False,
    }


def test_a_box_file_without_a_frame_is_in_sparse_0(tmp_path):
    file = tmp_path / "box.json"
    file.write_text(json.dumps({"lo": [0, 0, 0], "hi": [1, 1, 1]}))
    assert read_crop_box(file) == ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))


BAD_FILES = {
    "not JSON": ("{lo: [0, 0, 0]", "is not JSON"),
    "a list": ("[[0, 0, 0], [1, 1, 1]]", "has no lo and hi"),
    "no hi": ('{"lo": [0, 0, 0]}', "has no lo and hi"),
    "two numbers": ('{"lo": [0, 0], "hi": [1, 1, 1]}', "is not two corners of 3 numbers"),
    "text": ('{"lo": ["a", 0, 0], "hi": [1, 1, 1]}', "is not two corners of 3 numbers"),
    "x0 >= x1": ('{"lo": [1, 0, 0], "hi": [1, 1, 1]}', "is empty along x"),
    "infinite": ('{"lo": [0, 0, 0], "hi": [1, 1e999, 1]}', "not a finite number"),
    "other frame": ('{"frame": "colmap/sparse/0", "lo": [0, 0, 0], "hi": [1, 1, 1]}', "in frame 'colmap/sparse/0'"),
}


@pytest.mark.parametrize("case", list(BAD_FILES))
def test_a_bad_box_file_is_an_input_error(tmp_path, case):
    text, said = BAD_FILES[case]
    file = tmp_path / "box.json"
    file.write_text(text)
    with pytest.raises(InputError) as err:
        read_crop_box(file)
    assert said in err.value.problem and str(file) in err.value.problem and err.value.fix


@pytest.mark.parametrize(
    ("values", "said"),
    [
        (["0", "0", "0", "1", "1"], "takes 6 numbers or 1 file, not 5"),
        (["0", "0", "0", "1", "1", "z"], "is not six numbers"),
        (["0", "0", "2", "1", "1", "1"], "is empty along z"),
        (["0", "0", "0", "1", "inf", "1"], "not a finite number"),
        (["missing.json"], "does not exist"),
    ],
)
def test_bad_numbers_are_an_input_error(values, said):
    with pytest.raises(InputError, match=said):
        crop_box_from_args(values)


def test_clean_options_hold_the_box_as_floats():
    assert CleanOptions(crop_box=([0, 0, 0], [1, 2, 3])).crop_box == ((0.0, 0.0, 0.0), (1.0, 2.0, 3.0))
    with pytest.raises(InputError, match="not two corners"):
        CleanOptions(crop_box=5)


def test_the_cli_flag_sets_the_clean_options_box(tmp_path):
    from ffrecon import cli

    file = write_crop_box(tmp_path / "box.json", ((0, 0, 0), (1, 2, 3)))
    for given in (["0", "0", "0", "1", "2", "3"], [str(file)]):
        args = cli.parse_args(["run", "photos", "-o", str(tmp_path / "out"), "--crop-box", *given])
        assert cli._run_options(args).splat.clean == CleanOptions(crop_box=((0, 0, 0), (1, 2, 3)))
    args = cli.parse_args(["run", "photos", "-o", str(tmp_path / "out")])
    assert cli._run_options(args).splat.clean == CleanOptions()


@pytest.mark.parametrize("case", ["not JSON", "x0 >= x1", "two numbers"])
def test_a_bad_box_file_on_the_command_line_is_one_line_and_exit_2(tmp_path, capsys, case):
    from ffrecon import cli

    file = tmp_path / "box.json"
    file.write_text(BAD_FILES[case][0])
    code = cli.main(["run", str(tmp_path / "photos"), "-o", str(tmp_path / "out"), "--crop-box", str(file)])
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert code == 2 and "Traceback" not in err, err
    assert len(lines) == 2 and lines[0].startswith("ffrecon: error: crop box file") and BAD_FILES[case][1] in lines[0]
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_a_run_with_a_crop_box_keeps_only_the_gaussians_inside(full_run, demo12, tmp_path):
    """The demo run resumed with a box (the lower half of its automatic box, from a box file): only the splat
    stage runs again, and splat.ply holds only Gaussians inside; report.json names the box and its frame."""
    import dataclasses
    import shutil

    from ffrecon.formats.splat_ply import read_splat_ply
    from ffrecon.pipeline import RunOptions, run
    from ffrecon.splat.optimize import OptimizeOptions
    from ffrecon.splat.stage import SplatOptions

    auto = json.loads((full_run / "report.json").read_text())["splat"]["cleaning"]["crop_box"]
    assert auto["automatic"] and auto["frame"] == "sparse/0"
    lo, hi = np.array(auto["lo"]), np.array(auto["hi"])
    hi[2] = (lo[2] + hi[2]) / 2
    box = read_crop_box(write_crop_box(tmp_path / "box.json", (tuple(lo), tuple(hi))))
    out = tmp_path / "out"
    shutil.copytree(full_run, out, symlinks=True)
    splat = SplatOptions(video_frames=12, optimize=OptimizeOptions.brief(max_seconds=8.0, iterations=300))
    splat = dataclasses.replace(splat, clean=CleanOptions(crop_box=box))
    options = RunOptions(splat=splat, ground_truth=demo12.scene_dir, resume=True)
    assert run(demo12.images, out, demo12.model, options).exit_code == 0
    report = json.loads((out / "report.json").read_text())
    cleaning = report["splat"]["cleaning"]
    assert cleaning["crop_box"] == {"frame": "sparse/0", "lo": list(box[0]), "hi": list(box[1]), "automatic": False}
    assert cleaning["steps"][0]["step"] == "outside_crop_box" and cleaning["steps"][0]["applied"]
    assert cleaning["removed"]["outside_crop_box"] > 1000
    means = read_splat_ply(out / "splat.ply").means.numpy()
    assert len(means) == cleaning["count_after"]
    assert np.all(means >= np.array(box[0]) - 1e-5) and np.all(means <= np.array(box[1]) + 1e-5)
    assert (out / "camera_path.json").is_file() and (out / "flythrough.mp4").is_file()
