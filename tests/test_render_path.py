"""``ffrecon render OUT --camera-path PATH -o VIDEO``: the fly-through's own camera_path.json renders the
fly-through again, frame for frame; every bad input is one line and its exit code, before any rendering."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from ffrecon import cli
from ffrecon.formats.splat_ply import write_splat_ply
from ffrecon.gaussians import Gaussians
from ffrecon.geometry.poses import look_at_cam_from_world
from ffrecon.splat.video import write_flythrough
from ffrecon.types import PinholeCamera

FRAMES = 8


def _frames(video: Path) -> np.ndarray:
    capture = cv2.VideoCapture(str(video))
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(frame)
    capture.release()
    return np.stack(frames).astype(np.float64)


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a - b) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(255.0**2 / mse)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    """A run folder as the splat stage leaves it: a coloured cube of 3000 Gaussians in splat.ply, and the
    fly-through of the same splat (8 frames, 96x72) with its camera_path.json."""
    rng = np.random.default_rng(0)
    means = rng.uniform(-0.5, 0.5, size=(3000, 3))
    axis = rng.integers(0, 3, 3000)
    means[np.arange(3000), axis] = np.sign(rng.normal(size=3000)) * 0.5
    g = Gaussians.from_points(means, means + 0.5, np.full(3000, np.log(0.03)), opacity=0.8)
    g.sh = g.sh + torch.from_numpy(rng.normal(scale=0.1, size=g.sh.shape).astype(np.float32))
    angles = np.linspace(0, 1.5, 5)
    poses = np.stack(
        [look_at_cam_from_world(np.array([2.5 * np.cos(a), 2.5 * np.sin(a), 1.0]), np.zeros(3)) for a in angles]
    )
    out = tmp_path_factory.mktemp("tiny-run") / "out"
    write_splat_ply(out / "splat.ply", g)
    camera = PinholeCamera(97, 72, 80.0, 81.0, 47.0, 37.0)
    assert write_flythrough(out / "flythrough.mp4", g, poses, camera, num_frames=FRAMES, fps=12.0)
    return out


def _render(argv: list[str], capsys) -> tuple[int, str, str]:
    code = cli.main(["render", *map(str, argv)])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_the_fly_through_s_path_renders_the_fly_through_again(tiny_run, tmp_path, capsys):
    """Rendered from splat.ply along OUT/camera_path.json, every frame matches flythrough.mp4 (>= 40 dB)."""
    video = tmp_path / "again.mp4"
    code, out, err = _render([tiny_run, "--camera-path", tiny_run / "camera_path.json", "-o", video], capsys)
    assert code == 0, err
    assert f"{FRAMES} frames, 96x72 at 12 fps" in out
    fly, again = _frames(tiny_run / "flythrough.mp4"), _frames(video)
    assert fly.shape == again.shape == (FRAMES, 72, 96, 3)
    assert fly.std() > 10  # the splat fills the frames: a black video would match itself
    psnr = [_psnr(a, b) for a, b in zip(fly, again)]
    assert min(psnr) >= 40.0, psnr


def test_a_changed_path_renders_other_frames(tiny_run, tmp_path, capsys):
    """The render follows the file: a path moved sideways gives frames far from the fly-through's."""
    data = json.loads((tiny_run / "camera_path.json").read_text())
    for frame in data["camera_path"]:
        frame["camera_to_world"][3] += 0.3  # x of the camera centre
    moved = tmp_path / "moved.json"
    moved.write_text(json.dumps(data))
    code, _, err = _render([tiny_run, "--camera-path", moved, "-o", tmp_path / "moved.mp4"], capsys)
    assert code == 0, err
    psnr = [_psnr(a, b) for a, b in zip(_frames(tiny_run / "flythrough.mp4"), _frames(tmp_path / "moved.mp4"))]
    assert max(psnr) < 30.0, psnr


def _one_error(code: int, out: str, err: str, expected_code: int, said: str) -> None:
    lines = err.strip().splitlines()
    assert code == expected_code, err
    assert "Traceback" not in err and not out, err
    assert len(lines) == 2 and lines[0].startswith("ffrecon: error: ") and lines[1].startswith("  fix: "), lines
    assert said in lines[0], lines


@pytest.mark.parametrize(
    ("case", "text", "said"),
    [
        ("not JSON", "{keyframes", "is not JSON"),
        ("no keyframes", json.dumps({"render_width": 8, "render_height": 8, "fps": 1, "camera_path": []}), "no key"),
        (
            "wrong matrix shape",
            json.dumps(
                {"render_width": 8, "render_height": 8, "fps": 1, "keyframes": [{"matrix": [1, 0, 0], "fov": 50}]}
            ),
            "keyframes[0].matrix is not 16 finite numbers (3 values)",
        ),
    ],
)
def test_a_bad_path_file_is_one_line_and_exit_2(tiny_run, tmp_path, capsys, case, text, said):
    bad = tmp_path / "path.json"
    bad.write_text(text)
    video = tmp_path / "v.mp4"
    _one_error(*_render([tiny_run, "--camera-path", bad, "-o", video], capsys), 2, said)
    assert not video.exists()


def test_a_run_without_a_splat_is_exit_2_with_the_fix(tiny_run, tmp_path, capsys):
    bare = tmp_path / "bare"
    bare.mkdir()
    shutil.copy(tiny_run / "camera_path.json", bare)
    code, out, err = _render([bare, "--camera-path", bare / "camera_path.json", "-o", tmp_path / "v.mp4"], capsys)
    _one_error(code, out, err, 2, "has no splat.ply")
    assert "without --no-splat" in err


def test_an_existing_video_needs_overwrite(tiny_run, tmp_path, capsys):
    video = tmp_path / "v.mp4"
    video.write_bytes(b"mine")
    args = [tiny_run, "--camera-path", tiny_run / "camera_path.json", "-o", video]
    _one_error(*_render(args, capsys), 4, "exists")
    assert video.read_bytes() == b"mine"
    code, _, err = _render([*args, "--overwrite", "-q"], capsys)
    assert code == 0 and len(_frames(video)) == FRAMES, err


def test_the_video_must_be_mp4(tiny_run, tmp_path, capsys):
    args = [tiny_run, "--camera-path", tiny_run / "camera_path.json", "-o", tmp_path / "v.gif"]
    _one_error(*_render(args, capsys), 2, "is not an .mp4 file")


@pytest.mark.slow
def test_a_real_run_s_fly_through_renders_again(full_run, tmp_path, capsys):
    """The pipeline's own output folder: camera_path.json beside flythrough.mp4, rendered again from splat.ply."""
    video = tmp_path / "again.mp4"
    code, _, err = _render([full_run, "--camera-path", full_run / "camera_path.json", "-o", video], capsys)
    assert code == 0, err
    fly, again = _frames(full_run / "flythrough.mp4"), _frames(video)
    assert fly.shape == again.shape and fly.std() > 5
    psnr = [_psnr(a, b) for a, b in zip(fly, again)]
    assert min(psnr) >= 40.0, psnr
