"""The 3D view's points keep their colours although plotly does not check them one by one (issue 40: that check
was 0.9 s of every report): the figure is the one plotly builds when it checks everything."""

from __future__ import annotations

import json

import numpy as np
import plotly.graph_objects as go
import plotly.io as pio

from ffrecon.geometry.alignment import Sim3
from ffrecon.report import scene3d
from ffrecon.view.scene import CameraLayer, CameraSpec, Estimate, PointLayer


def _layer() -> CameraLayer:
    K = np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])
    cams = tuple(
        CameraSpec(f"f{k}.png", np.hstack([np.eye(3), [[0.1 * k], [0.0], [0.0]]]), k == 2, K, (64, 48))
        for k in range(4)
    )
    return CameraLayer(Estimate.FINAL, cams, Sim3(1.0, np.eye(3), np.zeros(3)), 0.0)


def test_the_unchecked_figure_is_the_checked_one():
    rng = np.random.default_rng(0)
    points = PointLayer(rng.random((300, 3)).astype(np.float32), rng.integers(0, 256, (300, 3), np.uint8), 300)
    figure = scene3d.scene_figure(_layer(), [], points)
    marker = figure["data"][0]["marker"]
    assert len(marker["color"]) == 300 and marker["color"][0] == "rgb({},{},{})".format(*points.rgb[0])
    checked = json.loads(pio.to_json(go.Figure(figure)))  # plotly checks every value and rebuilds the figure
    assert json.loads(pio.to_json(figure, validate=False)) == checked
