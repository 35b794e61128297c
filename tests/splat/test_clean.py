"""Cleaning: automatic and given crop boxes, low opacity, far away and isolated Gaussians."""

from __future__ import annotations

import numpy as np
import torch

from ffrecon.gaussians import Gaussians
from ffrecon.geometry.poses import look_at_cam_from_world
from ffrecon.splat.clean import CleanOptions, clean_gaussians
from ffrecon.types import PinholeCamera


def _scene(rng: np.random.Generator):
    # A dense unit-cube surface (the object), 5 far-away points, 5 isolated floaters near it, 20 faint ones.
    faces = rng.uniform(-0.5, 0.5, size=(6000, 3))
    axis = rng.integers(0, 3, 6000)
    faces[np.arange(6000), axis] = np.sign(rng.normal(size=6000)) * 0.5
    far = rng.normal(size=(5, 3)) * 0.1 + np.array([40.0, 0, 0])
    floaters = np.array([[1.2, 1.2, 1.2], [-1.3, 1.1, 0.9], [1.1, -1.2, -1.0], [-1.0, -1.1, 1.3], [0.0, 1.4, -1.2]])
    faint = rng.uniform(-0.5, 0.5, size=(20, 3))
    means = np.concatenate([faces, far, floaters, faint])
    opacity = np.full(len(means), 0.8)
    opacity[-20:] = 0.01
    g = Gaussians.from_points(means, np.full((len(means), 3), 0.5), np.full(len(means), np.log(0.01)), opacity=0.5)
    g.opacity_logits = torch.tensor(np.log(opacity / (1 - opacity)), dtype=torch.float32)
    angles = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    poses = np.stack(
        [look_at_cam_from_world(np.array([3 * np.cos(a), 3 * np.sin(a), 1.0]), np.zeros(3)) for a in angles]
    )
    cams = [PinholeCamera(64, 48, 60.0, 60.0, 32.0, 24.0)] * len(poses)
    return g, poses, cams


def test_automatic_cleaning_removes_outliers_and_keeps_the_object():
    g, poses, cams = _scene(np.random.default_rng(0))
    out, report = clean_gaussians(g, poses, cams, CleanOptions())
    kept = out.means.numpy()
    assert report.count_before == len(g) and report.count_after == len(out)
    assert len(out) >= 0.99 * 6000 and len(out) <= 6000  # the cube stays, nothing else
    assert np.abs(kept).max() <= 0.5 + 1e-5
    assert report.removed["low_opacity"] == 20
    lo, hi = np.array(report.crop_box[0]), np.array(report.crop_box[1])
    assert np.all(lo < -0.45) and np.all(hi > 0.45) and np.all(hi - lo < 1.5) and report.automatic_box


def test_given_crop_box():
    g, poses, cams = _scene(np.random.default_rng(1))
    box = ((-0.6, -0.6, 0.0), (0.6, 0.6, 0.6))
    out, report = clean_gaussians(g, poses, cams, CleanOptions(crop_box=box, floater_std_ratio=0))
    kept = out.means.numpy()
    assert kept[:, 2].min() >= 0.0 and not report.automatic_box
    expected = np.sum(g.means.numpy()[:6000, 2] >= 0)
    assert abs(len(out) - expected) <= 0


def _background_judge(g_full: Gaussians):
    """A stand-in for held-out PSNR in which the 5 far Gaussians are a background the views need (5 dB)."""
    far = {tuple(p) for p in g_full.means.numpy()[6000:6005].round(5)}

    def judge(g: Gaussians) -> float:
        kept = sum(tuple(p) in far for p in g.means.numpy().round(5))
        return 20.0 + kept  # 25 dB with the whole background, 20 without it

    return judge


def test_a_step_that_costs_held_out_psnr_is_skipped_and_reported():
    g, poses, cams = _scene(np.random.default_rng(0))
    out, report = clean_gaussians(g, poses, cams, CleanOptions(), judge=_background_judge(g))
    steps = {s.name: s for s in report.steps}
    far_step = next(s for s in report.steps if s.candidates and s.name in ("outside_crop_box", "far_away"))
    assert not far_step.applied and far_step.psnr_after == far_step.psnr_before - 5
    assert "skipped" in far_step.reason
    assert steps["low_opacity"].applied and steps["low_opacity"].candidates == 20  # costs nothing: kept
    assert len(out) == len(g) - 20 - sum(s.candidates for s in report.steps if s.applied and s.name != "low_opacity")
    assert np.isin(g.means.numpy()[6000:6005], out.means.numpy()).all()  # the background stays
    assert report.to_dict()["steps"][0]["psnr_before"] == 25.0


def test_a_given_crop_box_is_applied_whatever_it_costs():
    g, poses, cams = _scene(np.random.default_rng(0))
    box = ((-0.6, -0.6, -0.6), (0.6, 0.6, 0.6))
    _, report = clean_gaussians(g, poses, cams, CleanOptions(crop_box=box), judge=_background_judge(g))
    crop = report.steps[0]
    assert crop.name == "outside_crop_box" and crop.applied and crop.psnr_after == 20.0
    assert crop.reason.startswith("the crop box you gave")
