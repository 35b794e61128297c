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

from ffrecon.report import html as report_html
from ffrecon.report import scene3d
from ffrecon.view.scene import Estimate, PointLayer, ViewOptions, load_scene
from tests.conftest import CLIENTS


@pytest.fixture(scope="module")
def report(full_run):
    return json.loads((full_run / "report.json").read_text())


def test_the_view_shows_every_estimate_in_the_final_frame(full_run, report):
    page = scene3d.scene_html(report, full_run)
    figure = json.loads(re.search(r"Plotly.newPlot\(\s*\"scene3d\",\s*(\[.*?\]),\s*\{", page, re.S).group(1))
    names = [trace["name"] for trace in figure]
    assert names == [
        "points.ply",
        "final cameras",
        "flagged",
        "final centres",
        "feed-forward centres",
        "COLMAP centres",
    ], names
    flagged = {d["name"] for c in report["pose_errors"].values() for d in c["disagreeing"]}
    assert flagged == {"frame_007.png"}  # the demo model's one badly wrong frame
    hover = [t for t in figure if t["name"] == "feed-forward centres"][0]["text"]
    assert [h for h in hover if "flagged" in h] == ["feed-forward: frame_007.png (flagged)"]


def test_frustum_corners_are_the_image_corners_seen_by_the_camera(full_run):
    final = load_scene(full_run, ViewOptions(splat=False)).layer(Estimate.FINAL)
    lines = scene3d.frustum_lines(final.cameras, depth=0.3)
    assert len(lines) == 12 * len(final.cameras)
    cam = final.cameras[0]
    local = (lines[:11] - cam.world_from_cam[:, 3]) @ cam.world_from_cam[:, :3]  # world -> camera frame
    np.testing.assert_allclose(local[1], 0.0, atol=1e-9)  # the apex is the camera centre
    corners = local[[0, 2, 3, 5]]
    np.testing.assert_allclose(corners[:, 2], 0.3)  # in front of the camera (OpenCV: +z), at the depth
    px = corners @ cam.K.T
    w, h = cam.size_wh
    np.testing.assert_allclose(px[:, :2] / px[:, 2:], [[0, 0], [w, 0], [w, h], [0, h]], atol=1e-6)
    assert np.isnan(lines[11]).all()


def test_far_outliers_do_not_set_the_view_bounds():
    rng = np.random.default_rng(0)
    xyz = np.concatenate([rng.normal(size=(1000, 3)), [[500.0, 0, 0], [0, -800.0, 0]]]).astype(np.float32)
    kept, rgb = scene3d.without_far_points(PointLayer(xyz, np.zeros((len(xyz), 3), np.uint8), len(xyz)))
    assert len(kept) == len(rgb) and np.abs(kept).max() < 10 and len(kept) > 950


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
