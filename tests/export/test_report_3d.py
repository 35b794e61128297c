"""The report's pictures: the offline 3D view of cameras and points, the fly-through animation, the
flagged capture frames; and the page opened in headless Chromium with the network cut off."""

import base64
import io
import json
import re
import subprocess

import numpy as np
import pytest
from PIL import Image

from ffrecon.export import report_html
from ffrecon.export.scene3d import frustum_lines, load_camera_sets
from ffrecon.synthetic import load_scene
from tests.conftest import CLIENTS


@pytest.fixture(scope="module")
def report(full_run):
    return json.loads((full_run / "report.json").read_text())


def test_every_estimate_is_drawn_in_the_final_frame(full_run, report):
    sets = {s.label: s for s in load_camera_sets(full_run, report["inputs"]["names"])}
    assert list(sets) == ["final", "feed-forward", "COLMAP"]
    final = sets["final"]
    extent = np.linalg.norm(np.ptp(final.world_from_cam[:, :3, 3], axis=0))
    for label in ("feed-forward", "COLMAP"):
        other = sets[label]
        common = [n for n in other.names if n in final.names]
        assert len(common) >= 10
        a = np.array([other.world_from_cam[other.names.index(n), :3, 3] for n in common])
        b = np.array([final.world_from_cam[final.names.index(n), :3, 3] for n in common])
        # Aligned by a Sim(3) on the centres: they sit on the final centres to within a few percent of the
        # extent (the simulated model's injected error and COLMAP's noise, not a frame or scale mistake).
        assert np.median(np.linalg.norm(a - b, axis=1)) < 0.05 * extent, label
        disagreeing = {d["name"] for c in report["pose_errors"].values() for d in c["disagreeing"]}
        for n in set(common) - disagreeing:  # orientations carried along: a frame mistake is tens of degrees
            ra = other.world_from_cam[other.names.index(n), :3, :3]
            rb = final.world_from_cam[final.names.index(n), :3, :3]
            angle = np.degrees(np.arccos(np.clip((np.trace(ra.T @ rb) - 1) / 2, -1, 1)))
            assert angle < 5.0, (label, n, angle)


def test_final_cameras_match_ground_truth_up_to_similarity(full_run, report, demo12):
    scene = load_scene(demo12.scene_dir)
    final = load_camera_sets(full_run, report["inputs"]["names"])[0]
    truth = {n: -p[:, :3].T @ p[:, 3] for n, p in zip(scene.names, scene.cam_from_world)}
    from ffrecon.geometry.alignment import umeyama

    est = final.world_from_cam[:, :3, 3]
    gt = np.array([truth[n] for n in final.names])
    fit = umeyama(est, gt)
    assert np.sqrt(np.mean(np.sum((fit.apply(est) - gt) ** 2, axis=1))) < 0.02 * np.linalg.norm(np.ptp(gt, axis=0))


def test_frustum_corners_are_the_image_corners_seen_by_the_camera(full_run, report):
    final = load_camera_sets(full_run, report["inputs"]["names"])[0]
    lines = frustum_lines(final, depth=0.3)
    assert len(lines) == 12 * len(final.names)
    first = lines[:11]
    world_from_cam = final.world_from_cam[0]
    cam = (first - world_from_cam[:3, 3]) @ world_from_cam[:3, :3]  # world -> camera frame
    np.testing.assert_allclose(cam[1], 0.0, atol=1e-12)  # the apex is the camera centre
    corners = cam[[0, 2, 3, 5]]
    np.testing.assert_allclose(corners[:, 2], 0.3)  # in front of the camera (OpenCV: +z), at the depth
    px = corners @ final.K[0].T
    w, h = final.size_wh[0]
    np.testing.assert_allclose(px[:, :2] / px[:, 2:], [[0, 0], [w, 0], [w, h], [0, h]], atol=1e-9)
    assert np.isnan(lines[11]).all()


def test_the_page_has_the_3d_view_the_flythrough_and_the_flagged_frames(full_run, report):
    page = report_html.render_html(report, full_run)
    assert page.count('id="scene3d"') == 1 and "Plotly.newPlot" in page
    webp = re.search(r"src='data:image/webp;base64,([^']+)'", page)
    assert webp is not None, "the fly-through animation is missing"
    animation = Image.open(io.BytesIO(base64.b64decode(webp.group(1))))
    assert animation.is_animated and animation.n_frames >= 8
    flagged = {f["name"] for f in report["inputs"]["quality"]["flags"]}
    assert flagged, "the 12-frame demo scene has frames with too little overlap; the test relies on them"
    framed = re.findall(r"<figure class=flagged>.*?<figcaption>([^<:]+):", page)
    assert set(framed) == flagged


@pytest.mark.slow
def test_report_opens_offline_with_an_interactive_3d_view(full_run, chromium, node_clients, tmp_path):
    png = tmp_path / "report.png"
    cmd = ["node", "open_offline.mjs", str(full_run / "report.html"), str(png), "1100", "800"]
    out = subprocess.run(
        [*cmd, "#scene3d .gl-container canvas"], cwd=CLIENTS, capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr[-2000:]
    seen = json.loads(out.stdout.strip().splitlines()[-1])
    assert seen["external_requests"] == []
    assert seen["console_errors"] == []
    assert seen["found"], "plotly drew no WebGL canvas for the 3D view"
    shot = np.asarray(Image.open(png).convert("RGB")).astype(float)
    # The view scrolled into sight: frustums and points make a busy picture, not a blank page.
    assert shot.std() > 20 and len(np.unique(shot.reshape(-1, 3), axis=0)) > 500
