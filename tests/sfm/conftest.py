"""Shared synthetic scenes, simulated predictions and COLMAP runs for the sfm tests (session-scoped).

The prediction is built directly from the simulated model's injected errors (SimulatedTruth), so these
tests do not depend on the ONNX path.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

from ffrecon.sfm.crosscheck.options import ColmapOptions
from ffrecon.sfm.crosscheck.run import ColmapResult, run_colmap
from ffrecon.sfm.refine.options import RefineInputs, RefineOptions, RefineResult
from ffrecon.sfm.refine.run import run_refine
from ffrecon.synthetic import SceneOptions, SyntheticScene, Texture, make_scene, write_scene
from ffrecon.synthetic.simulated_model import SimulationOptions, prediction_from_truth, simulate
from ffrecon.types import Prediction


@dataclass(frozen=True)
class Capture:
    scene: SyntheticScene
    image_dir: Path
    prediction: Prediction


def _capture(tmp_path_factory, options: SceneOptions, truth_of: Capture | None = None) -> Capture:
    scene = make_scene(options)
    image_dir = write_scene(scene, tmp_path_factory.mktemp("scene"))
    if truth_of is not None:  # same geometry and poses: the injected errors carry over exactly
        prediction = Prediction(
            scene.names,
            *[getattr(truth_of.prediction, f) for f in ("cam_from_world", "cameras", "depth", "depth_conf", "model")],
        )
        return Capture(scene, image_dir, prediction)
    sim = SimulationOptions(seed=0)
    truth, _ = simulate(scene, sim)
    return Capture(scene, image_dir, prediction_from_truth(scene, truth, sim))


@pytest.fixture(scope="session")
def orbit24(tmp_path_factory) -> Capture:
    """24 frames 320x240, rich texture, orbit; simulated model with 2.5 deg / 3% / 3% errors."""
    return _capture(tmp_path_factory, SceneOptions(num_frames=24, width=320, height=240, seed=0))


@pytest.fixture(scope="session")
def one_flat_frame24(tmp_path_factory, orbit24) -> Capture:
    """The same capture with frame 5 nearly textureless."""
    return _capture(
        tmp_path_factory, SceneOptions(num_frames=24, width=320, height=240, seed=0, textureless_frames=(5,)), orbit24
    )


@pytest.fixture(scope="session")
def repeated24(tmp_path_factory, orbit24) -> Capture:
    """The same capture with one tile repeated on every surface (look-alike views)."""
    return _capture(
        tmp_path_factory, SceneOptions(num_frames=24, width=320, height=240, seed=0, texture=Texture.REPEATED), orbit24
    )


@pytest.fixture(scope="session")
def colmap24(orbit24, tmp_path_factory) -> tuple[ColmapResult, Path]:
    out = tmp_path_factory.mktemp("colmap")
    focal = [c.fx for c in orbit24.prediction.cameras]
    return run_colmap(orbit24.image_dir, orbit24.scene.names, ColmapOptions(), out, focal_prior_px=focal), out


@pytest.fixture(scope="session")
def refined24(orbit24, colmap24, tmp_path_factory) -> tuple[RefineResult, Path]:
    out = tmp_path_factory.mktemp("refine")
    inputs = RefineInputs(orbit24.image_dir, reuse_features_from=colmap24[0].database_path)
    return run_refine(inputs, orbit24.prediction, RefineOptions(), out), out
