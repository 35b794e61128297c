"""Issue 39 end to end: on look-alike surfaces, two unfiltered SIFT pairs a pattern's period off do not reseed a
frame the model had right.

The repeated-tile object of held-out seed 264 (``tools/sweep_families.py``: orbited 50-90 deg a step, a 50-deg lens,
the simulated model 2.5 deg / 3 % off, through ONNX as a user runs it). Two of frame 3's seven verified pairs agree
on a rotation 86 deg from the model's (1.1 deg from the truth; the object is square and tiled alike on every side).
The refinement started frame 3 there, dense tracks held it there, and it was left out ("neither pose can be
trusted") in every run of that scene. Once the guidance finds the surfaces look alike, the frame starts from the
model's camera."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap

from ffrecon.geometry.metrics import aligned_rotation_errors_deg
from ffrecon.pipeline import RunOptions, run
from ffrecon.splat.stage import SplatOptions
from ffrecon.synthetic import CameraPath, SceneOptions, Texture, make_scene, write_scene
from ffrecon.synthetic.layouts import Layout
from ffrecon.synthetic.simulated_model import SimulationOptions, build_simulated_vggt

LUND = Path(__file__).resolve().parents[2] / "shared" / "data" / "lund"


def test_a_frame_two_sift_pairs_put_a_period_off_starts_from_the_models_camera(tmp_path, caplog):
    options = SceneOptions(
        num_frames=8,
        width=320,
        height=240,
        seed=264,
        path=CameraPath.WIDE,
        layout=Layout.OBJECT,
        texture=Texture.REPEATED,
        step_deg=(50.0, 90.0),
        fov_x_deg=50.0,
        photo_dir=str(LUND),  # as the sweep draws it
    )
    scene = make_scene(options)
    images = write_scene(scene, tmp_path / "scene")
    build_simulated_vggt(scene, tmp_path / "sim.onnx", SimulationOptions(seed=264))
    with caplog.at_level("WARNING", logger="ffrecon"):
        run(images, tmp_path / "out", tmp_path / "sim.onnx", RunOptions(splat=SplatOptions(enabled=False)))
    said = caplog.text
    # the screen did find frame 3 a suspect (else this test would test nothing), and its reseeding was undone
    assert "frame_003.png: 2 of its 7 verified pairs put it" in said
    assert "the verified pairs that put frame_003.png far from the model's rotation are not trusted" in said
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["refine"]["screened"] == []
    rec = pycolmap.Reconstruction(str(tmp_path / "out" / "sparse" / "0"))
    by_name = {im.name: im for im in rec.images.values() if im.has_pose}
    assert sorted(by_name) == list(scene.names)  # every frame exported, frame 3 among them
    poses = np.stack([by_name[n].cam_from_world().matrix()[:, :3] for n in scene.names])
    errors = aligned_rotation_errors_deg(poses, scene.cam_from_world[:, :, :3])
    # measured 0.03-0.2 deg per frame (the model's 1.1-2.8); issue 39's bar for a run is half the model's median
    assert errors[3] < 2.0 and np.median(errors) < 1.0, errors.round(2)
