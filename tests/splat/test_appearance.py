"""Per-image exposure and white-balance compensation: the closed-form fit used for held-out views, the
transforms' survival through densification, and the end-to-end gain on photos whose exposure varies."""

from __future__ import annotations

import numpy as np
import torch

from ffrecon.gaussians import Gaussians
from ffrecon.splat.appearance import (
    apply_color_transform,
    change_photo_colors,
    fit_color_transform,
    random_color_changes,
)
from ffrecon.splat.densify import Densifier, DensifyOptions
from ffrecon.splat.optimize import OptimizeOptions
from ffrecon.splat.stage import SplatOptions, color_corrected, image_metrics, run_splat, split_views
from ffrecon.splat.trainable import _densify, _trainable
from ffrecon.synthetic import SceneOptions, make_scene


def test_fit_color_transform_recovers_an_affine_change_and_skips_clipped_pixels():
    gen = torch.Generator().manual_seed(0)
    source = torch.rand(40, 50, 3, generator=gen)
    truth = torch.tensor([[1.2, 0.1, 0.0, 0.05], [0.0, 0.9, -0.1, -0.02], [0.05, 0.0, 1.1, 0.0]])
    target = apply_color_transform(source, truth).clamp(0, 1)  # bright pixels clip
    assert float((target == 1).any(dim=2).float().mean()) > 0.1
    fitted = fit_color_transform(source, target, ridge=0.0)
    assert torch.allclose(fitted.float(), truth, atol=1e-4)
    # The light default ridge barely moves it; a flat source gives a tame answer, not a singular one.
    assert torch.allclose(fit_color_transform(source, target).float(), truth, atol=0.02)
    flat = fit_color_transform(torch.full((10, 3), 0.5), torch.full((10, 3), 0.6))
    assert torch.isfinite(flat).all() and float(flat[:, :3].diagonal().min()) > 0.5
    corrected = color_corrected(source, target)
    assert image_metrics(corrected, target)[0] > 60.0 > image_metrics(source, target)[0]


def test_densification_leaves_the_colour_transforms_and_their_adam_state_alone():
    rng = np.random.default_rng(0)
    g = Gaussians.from_points(rng.normal(size=(50, 3)), rng.uniform(size=(50, 3)), np.full(50, -3.0), opacity=0.5)
    options = OptimizeOptions(sh_degree=0, densify=DensifyOptions(grad_threshold=0.0))
    params, adam = _trainable(g, options, scale=1.0, num_views=4, refine_poses=options.refine_poses)
    for p in params.values():
        p.grad = torch.ones_like(p)
    adam.step()
    deltas, state = params["color_deltas"], dict(adam.state[params["color_deltas"]])
    densifier = Densifier(50, options.densify, 1.0, max_gaussians=80, seed=0)
    densifier.accumulate(torch.ones(50, 2), torch.ones(50, dtype=torch.bool), width=10, height=10)
    resized = _densify(densifier, params, adam)
    assert len(resized["means"]) == 80 and resized["color_deltas"] is deltas
    group = next(gr for gr in adam.param_groups if gr["name"] == "color_deltas")
    assert group["params"] == [deltas] and group["lr"] == options.lr_appearance
    assert all(torch.equal(adam.state[deltas][k], v) for k, v in state.items() if torch.is_tensor(v))


def _exposure_run(scene, images, appearance: bool, tmp_path):
    train, _ = split_views(len(scene), 8)
    xyz = np.concatenate([scene.frame_points(i).reshape(-1, 3) for i in train])
    rgb = np.concatenate([images[i].reshape(-1, 3) for i in train]).astype(np.float32) / 255.0
    optimize = OptimizeOptions.brief(
        iterations=400, max_seconds=1e9, progress=False, sh_degree=1, threads=1, appearance=appearance
    )
    options = SplatOptions(max_seed_points=3000, video=False, device="cpu", report_views=0, optimize=optimize)
    cameras = [scene.camera] * len(scene)
    return run_splat(images, scene.names, scene.cam_from_world, cameras, xyz, rgb, options, tmp_path / str(appearance))


def test_compensation_helps_when_exposure_and_white_balance_vary(tmp_path):
    """Every photo (held-out ones too) gets its own channel gains in [0.7, 1.3] and offsets within 0.03.

    Measured (17 views at 64x48, 14 trained on, 400 iterations, default rates, 1 thread): colour-corrected
    held-out PSNR 20.96 dB without compensation, 21.44 dB with (SSIM 0.744 -> 0.761); the learnt
    per-channel gains, against the applied ones divided by their mean over the training views (the
    gauge: the learnt transforms average [I | 0]), have a mean absolute error of 0.082 where the
    applied ones spread by 0.141, correlation 0.96. Each view is visited ~29 times here, so the
    transforms are only part-way there (0.031 at ``lr_appearance=5e-3``).
    """
    scene = make_scene(SceneOptions(num_frames=17, width=64, height=48))
    changes = random_color_changes(len(scene), gain_spread=0.3, offset_spread=0.03, seed=0)
    images = [change_photo_colors(im, t) for im, t in zip(scene.images, changes)]
    plain = _exposure_run(scene, images, False, tmp_path)
    compensated = _exposure_run(scene, images, True, tmp_path)

    key = "psnr_cleaned_color_corrected"
    gain_db = compensated.mean(key) - plain.mean(key)
    train = list(compensated.train)
    learnt = np.stack([np.diag(t[:, :3]) for t in compensated.color_transforms[train]])
    applied = np.stack([np.diag(t[:, :3]) for t in changes[train]])
    applied = applied / applied.mean(axis=0)  # the learnt ones average [I | 0] over the training views
    error, spread = np.abs(learnt - applied).mean(), np.abs(applied - 1).mean()
    correlation = np.corrcoef(learnt.ravel(), applied.ravel())[0, 1]
    print(f"{key}: {plain.mean(key):.2f} -> {compensated.mean(key):.2f} dB; gain error {error:.3f} of {spread:.3f}")
    assert gain_db > 0.25, (plain.mean(key), compensated.mean(key))
    assert compensated.mean("ssim_cleaned_color_corrected") > plain.mean("ssim_cleaned_color_corrected") + 0.008
    assert correlation > 0.9 and error < 0.75 * spread, (correlation, error, spread)
    assert np.allclose(plain.color_transforms, np.eye(3, 4)) and np.allclose(learnt.mean(axis=0), 1.0)
    assert np.allclose(compensated.color_transforms[list(compensated.heldout)], np.eye(3, 4))
    # Cleaning's defaults still fit: it removes no more with compensation, and nothing the views need.
    kept = [r.count_cleaned / r.count_optimized for r in (plain, compensated)]
    assert kept[1] >= kept[0] - 0.02, kept
    assert compensated.mean("psnr_cleaned") >= compensated.mean("psnr_optimized") - 0.2


def test_random_color_changes_are_seeded_and_zero_spread_changes_nothing():
    image = np.arange(48, dtype=np.uint8).reshape(4, 4, 3)
    (change,) = random_color_changes(1, gain_spread=0.0, offset_spread=0.0)
    assert np.array_equal(change, np.eye(3, 4)) and np.array_equal(change_photo_colors(image, change), image)
    assert np.array_equal(random_color_changes(3, seed=5), random_color_changes(3, seed=5))
