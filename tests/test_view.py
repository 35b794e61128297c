"""``ffrecon view``: the scene it builds from an output folder, its CLI errors, and the page in headless Chromium."""

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import torch

from ffrecon.errors import InputError
from ffrecon.gaussians import SH_C0
from ffrecon.view import Estimate, ViewOptions, load_scene
from ffrecon.view.scene import FLAG_COLOR, image_flags, splat_layer
from ffrecon.view.server import _camera_markdown
from tests.conftest import ctrl_c_default

REPO = Path(__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _copy_run(full_run: Path, dst: Path, *, drop: tuple[str, ...] = ()) -> Path:
    """A light copy of the output folder (models, report, points, splat, images), less ``drop``."""
    keep = {"report.json", "points.ply", "splat.ply", "images", "sparse", "crosscheck", "feedforward"} - set(drop)
    dst.mkdir()
    for item in full_run.iterdir():
        if item.name in keep:
            ignore = shutil.ignore_patterns("depth", "database.db")
            (shutil.copytree(item, dst / item.name, ignore=ignore) if item.is_dir() else shutil.copy(item, dst))
    return dst


@pytest.fixture(scope="module")
def scene(full_run):
    return load_scene(full_run)


def test_each_estimate_has_its_colour_and_all_cameras(scene, full_run):
    assert [layer.estimate for layer in scene.layers] == list(Estimate)
    assert len({layer.color for layer in scene.layers} | {FLAG_COLOR}) == 4
    report = json.loads((full_run / "report.json").read_text())
    assert all(len(layer.cameras) == report["inputs"]["num_frames"] for layer in scene.layers)
    assert scene.missing == ()
    assert len(scene.points.xyz) == scene.points.total > 1000
    assert len(scene.splat.centers) == scene.splat.total > 1000


def test_flagged_frames_are_those_the_report_flags(scene, full_run):
    report = json.loads((full_run / "report.json").read_text())
    expected = {d["name"] for d in report["pose_errors"]["feedforward_vs_colmap"]["disagreeing"]}
    expected |= set(report["colmap"]["unregistered"])
    evidence = report["evidence"]["per_image"]
    expected |= {e["name"] for e in evidence if e["verdict"] != "confirmed" or e["status"] == "COLMAP only"}
    assert expected, "the synthetic run should flag a frame (the simulated model's noisy one), or nothing is tested"
    assert set(scene.flagged) == expected
    for layer in scene.layers:
        assert {c.name for c in layer.cameras if c.flagged} == expected
    name = sorted(expected)[0]
    text = _camera_markdown(scene, scene.layers[0], next(c for c in scene.layers[0].cameras if c.name == name))
    assert name in text and "**flagged**" in text and "feedforward vs colmap: rotation" in text
    assert scene.images[name].path == full_run / "images" / name


def test_image_flags_reads_every_kind_of_flag():
    report = {
        "pose_errors": {
            "feedforward_vs_colmap": {"estimate": "feed-forward", "disagreeing": [{"name": "a", "reason": "off"}]},
            "refined_vs_ground_truth": {"estimate": "refined", "disagreeing": [{"name": "gt", "reason": "x"}]},
        },
        "colmap": {"unregistered": ["b"]},
        "evidence": {
            "per_image": [
                {"name": "c", "verdict": "unchecked", "status": "unchecked", "why": "no inliers"},
                {"name": "d", "verdict": "confirmed", "status": "refined on image matches", "why": "bundle-adjusted"},
                {"name": "e", "verdict": "confirmed", "status": "confirmed by COLMAP", "why": "agrees"},
                {"name": "f", "verdict": "contradicted", "status": "disagrees with COLMAP", "why": "off"},
            ]
        },
    }
    flags = image_flags(report)
    assert set(flags) == {"a", "b", "c", "f"}
    assert flags["a"] == ["feed-forward vs COLMAP: off"]
    assert image_flags({"colmap": {"skipped": "quick mode"}, "evidence": {"skipped": "x"}}) == {}


def test_colmap_cameras_sit_on_the_final_ones_after_alignment(scene):
    final = {c.name: c.world_from_cam[:, 3] for c in scene.layer(Estimate.FINAL).cameras}
    extent = np.linalg.norm(np.ptp(np.array(list(final.values())), axis=0))
    colmap = scene.layer(Estimate.COLMAP)
    gaps = [np.linalg.norm(c.world_from_cam[:, 3] - final[c.name]) for c in colmap.cameras]
    assert max(gaps) < 0.01 * extent
    # and the fit did the work: COLMAP's own frame has another scale and origin
    raw = colmap.final_from_layer.inverse().apply(np.array([c.world_from_cam[:, 3] for c in colmap.cameras]))
    assert np.max(np.linalg.norm(raw - np.array([final[c.name] for c in colmap.cameras]), axis=1)) > 0.1 * extent
    final_rot = {c.name: c.world_from_cam[:, :3] for c in scene.layer(Estimate.FINAL).cameras}
    rot_gap = [np.linalg.norm(c.world_from_cam[:, :3] - final_rot[c.name]) for c in colmap.cameras]
    assert max(rot_gap) < 0.05


def test_missing_layers_are_skipped_and_said(full_run, tmp_path):
    out = _copy_run(full_run, tmp_path / "quick", drop=("crosscheck", "splat.ply"))
    scene = load_scene(out, ViewOptions(max_points=500))
    assert [layer.estimate for layer in scene.layers] == [Estimate.FEEDFORWARD, Estimate.FINAL]
    assert dict(scene.missing) == {"COLMAP cameras": "no model in crosscheck/sparse/0", "splat": "no splat.ply"}
    assert scene.splat is None and len(scene.points.xyz) == 500 < scene.points.total


def test_bad_folders_raise_readable_errors(full_run, tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        load_scene(tmp_path / "nowhere")
    (tmp_path / "photos").mkdir()
    with pytest.raises(InputError, match="not an ffrecon output folder"):
        load_scene(tmp_path / "photos")
    out = _copy_run(full_run, tmp_path / "corrupt", drop=("images",))
    data = (out / "splat.ply").read_bytes()
    (out / "splat.ply").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="splat.ply") as err:
        load_scene(out)
    assert "delete splat.ply" in err.value.fix


def test_splat_layer_covariances_colours_and_cap():
    from ffrecon.gaussians import Gaussians

    angle = 0.7  # about z
    quat = torch.tensor([np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2)], dtype=torch.float32)
    g = Gaussians(
        means=torch.arange(9, dtype=torch.float32).reshape(3, 3),
        quats_wxyz=torch.stack([quat * 2.0] * 3),  # unnormalised on purpose
        log_scales=torch.log(torch.tensor([[0.1, 0.2, 0.3]] * 3)),
        opacity_logits=torch.tensor([-1.0, 2.0, 0.0]),
        sh=torch.zeros(3, 4, 3),
    )
    layer = splat_layer(g, max_gaussians=2)
    assert layer.total == 3 and np.allclose(layer.centers, [[3, 4, 5], [6, 7, 8]])  # the two most opaque
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    assert np.allclose(layer.covariances[0], rot @ np.diag([0.01, 0.04, 0.09]) @ rot.T, atol=1e-6)
    assert np.allclose(layer.rgbs, 0.5) and np.isclose(SH_C0, 0.28209479177387814)
    assert np.allclose(layer.opacities[:, 0], [1 / (1 + np.exp(-2.0)), 0.5])


def _start_viewer(out: Path, port: int, *extra: str) -> tuple[subprocess.Popen, str]:
    """``ffrecon view`` as a subprocess; returns it and its address line (waits at most 60 s)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "ffrecon", "view", str(out), "--port", str(port), *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO,
        preexec_fn=ctrl_c_default,
    )
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.append(proc.stdout.readline()), daemon=True)
    reader.start()
    reader.join(timeout=60)
    if not lines or not lines[0]:
        proc.kill()
        _, err = proc.communicate(timeout=10)
        pytest.fail(f"no address line within 60 s; stderr: {err}")
    return proc, lines[0]


def _stop(proc: subprocess.Popen) -> tuple[int, str]:
    proc.send_signal(signal.SIGINT)
    try:
        _, err = proc.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        pytest.fail("the viewer did not stop within 10 s of Ctrl-C")
    return proc.returncode, err


def test_cli_reports_a_taken_port_and_a_missing_folder(full_run, tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        run = subprocess.run(
            [sys.executable, "-m", "ffrecon", "view", str(full_run), "--port", str(port)],
            capture_output=True,
            text=True,
            timeout=60,
            cwd=REPO,
        )
    assert run.returncode == 2, run.stdout + run.stderr
    assert f"127.0.0.1:{port}: the port is in use" in run.stderr and "--port" in run.stderr
    assert "Traceback" not in run.stderr
    from ffrecon.cli import main

    assert main(["view", str(tmp_path / "nowhere")]) == 2


@pytest.mark.slow
def test_viewer_page_shows_the_scene_and_stops_on_ctrl_c(full_run, chromium, node_clients, tmp_path):
    port = _free_port()
    proc, line = _start_viewer(full_run, port, "--max-points", "30000", "--max-gaussians", "20000")
    try:
        assert line.startswith(f"viewer: http://127.0.0.1:{port}/?token="), line
        url = line.split()[1]  # as printed: the page loads with its token, its WebSocket with the cookie
        shown, hidden = tmp_path / "shown.png", tmp_path / "hidden.png"
        shot = subprocess.run(
            ["node", "screenshot_url.mjs", url, shown, "1000x700", "30000", "3000", hidden],
            cwd=REPO / "clients",
            capture_output=True,
            text=True,
            timeout=120,
            env={**os.environ, "CHROMIUM": str(chromium)},
        )
        assert shot.returncode == 0, shot.stderr
        result = json.loads(shot.stdout.strip().splitlines()[-1])
    finally:
        code, err = _stop(proc)
    assert code == 0 and "Traceback" not in err and err.strip().splitlines()[-1] == "ffrecon: viewer stopped", err
    assert result["canvas"] and result["blocked"] == []
    assert result["unchecked"]["clicked"] == [
        "feed-forward cameras",
        "COLMAP cameras",
        "final cameras",
        "points",
        "splat",
        "show crop box",
    ]
    viser_splat_warning = "computeBoundingSphere(): Computed radius is NaN"  # viser's splat mesh, any splat
    assert [e for e in result["console_errors"] if viser_splat_warning not in e] == []

    from PIL import Image

    def scene_region(path):  # left of the GUI panel, below the software-WebGL notice
        return np.asarray(Image.open(path).convert("RGB"), dtype=np.int16)[170:680, 0:590]

    on, off = scene_region(shown), scene_region(hidden)
    near_white = (off > 235).all(axis=-1).mean()
    assert near_white > 0.95, f"with every layer hidden the view should be empty, {near_white:.0%} background"
    changed = (np.abs(on - off).max(axis=-1) > 40).mean()
    assert changed > 0.3, f"only {changed:.0%} of the view differs from the empty one: the scene is not drawn"
    colours = len(np.unique((on // 32).reshape(-1, 3), axis=0))
    assert colours > 60, f"{colours} distinct colours: a flat image, not the splat and points"

    def box_pixels(image):  # the crop box's magenta lines (ffrecon.view.panel.BOX_COLOR); the scene alone has ~15
        return int(((image[..., 0] > 180) & (image[..., 2] > 180) & (image[..., 1] < 90)).sum())

    assert box_pixels(on) > 80 and box_pixels(off) == 0, (box_pixels(on), box_pixels(off))


def test_selecting_a_camera_shows_its_photo_and_errors(scene):
    from ffrecon.view import start_viewer

    viewer = start_viewer(scene, port=_free_port())
    try:
        name = scene.flagged[0]
        viewer.select(Estimate.COLMAP, name)
        assert name in viewer.details.content and "COLMAP camera" in viewer.details.content
        assert "**flagged**" in viewer.details.content
        assert viewer.photo.visible and viewer.photo.image.shape == (240, 320, 3)
        with pytest.raises(KeyError):
            viewer.select(Estimate.FINAL, "no-such-frame.png")
    finally:
        viewer.stop()
