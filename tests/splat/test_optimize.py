"""Brief optimisation on tiny scenes: it fits, refines a perturbed camera, densifies as designed."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from ffrecon.gaussians import Gaussians, rgb_to_sh_dc
from ffrecon.geometry.poses import look_at_cam_from_world
from ffrecon.geometry.rotations import axis_angle_to_matrix, rotation_angle_deg
from ffrecon.splat.densify import Densifier, DensifyOptions, replace_rows
from ffrecon.splat.optimize import OptimizeOptions, optimize
from ffrecon.splat.render import render
from ffrecon.splat.ssim import ssim_map
from ffrecon.splat.train_views import downscaled, resolution_factor

W, H = 64, 48
K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])


def _truth(rng: np.random.Generator, n: int = 400) -> Gaussians:
    """Small opaque Gaussians with random colours on a bumpy plane z ~ 0 (the scene to recover)."""
    xy = rng.uniform(-1, 1, size=(n, 2))
    means = np.concatenate([xy, 0.05 * np.sin(4 * xy[:, :1])], axis=1)
    g = Gaussians.from_points(means, rng.uniform(0, 1, (n, 3)), np.full(n, np.log(0.06)), opacity=0.9)
    g.log_scales[:, 2] = np.log(0.01)
    return g


def _cameras(num: int) -> np.ndarray:
    angles = np.linspace(-0.6, 0.6, num)
    return np.stack(
        [
            look_at_cam_from_world(
                np.array([2.2 * np.sin(a), -0.4, 2.2 * np.cos(a)]), np.zeros(3), up=np.array([0, -1.0, 0])
            )
            for a in angles
        ]
    )


def _images(g: Gaussians, poses: np.ndarray) -> list[torch.Tensor]:
    with torch.no_grad():
        return [
            render(
                g.means,
                g.quats_wxyz,
                g.log_scales,
                g.opacity_logits,
                g.sh,
                torch.tensor(p, dtype=torch.float32),
                torch.tensor(K, dtype=torch.float32),
                W,
                H,
                sh_degree=0,
            ).rgb
            for p in poses
        ]


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(10 * torch.log10(1 / torch.mean((a.clamp(0, 1) - b) ** 2)))


def test_optimisation_fits_held_out_views():
    rng = np.random.default_rng(0)
    truth = _truth(rng)
    poses = _cameras(7)
    images = _images(truth, poses)
    seed = truth.detached()
    seed.means += torch.tensor(rng.normal(scale=0.03, size=seed.means.shape), dtype=torch.float32)
    seed.sh[:, 0] = rgb_to_sh_dc(torch.tensor(rng.uniform(0.3, 0.7, (len(seed), 3)), dtype=torch.float32))
    seed.opacity_logits[:] = float(np.log(0.1 / 0.9))
    test, train = [3], [0, 1, 2, 4, 5, 6]
    before = _psnr(_images(seed, poses[test])[0], images[3])
    options = OptimizeOptions(iterations=150, sh_degree=0, densify=None, progress=False, lr_means=1e-3)
    result = optimize(seed, images, poses, np.stack([K] * 7), train, options, scale=1.0)
    after = _psnr(_images(result.gaussians, poses[test])[0], images[3])
    assert result.iterations == 150 and len(result.history) == 15
    assert after > before + 6.0, (before, after)
    assert result.history[-1][2] < 0.5 * result.history[0][2]


def test_pose_refinement_recovers_a_perturbed_camera():
    rng = np.random.default_rng(1)
    truth = _truth(rng, 600)
    poses = _cameras(4)
    images = _images(truth, poses)
    perturbed = poses.copy()
    delta = axis_angle_to_matrix(np.radians(1.5) * np.array([0.6, -0.8, 0.0]))
    perturbed[2] = np.concatenate(
        [delta @ poses[2][:, :3], delta @ poses[2][:, 3:] + np.array([[0.03], [-0.02], [0.0]])], axis=1
    )
    frozen = {
        "lr_means": 0.0,
        "lr_means_final": 0.0,
        "lr_sh_dc": 0.0,
        "lr_sh_rest": 0.0,
        "lr_opacity": 0.0,
        "lr_scales": 0.0,
        "lr_quats": 0.0,
    }
    options = OptimizeOptions(
        iterations=240,
        sh_degree=0,
        densify=None,
        progress=False,
        refine_poses=True,
        lr_pose_rotation=2e-3,
        lr_pose_translation=2e-3,
        ssim_weight=0.0,
        **frozen,
    )
    result = optimize(truth, images, perturbed, np.stack([K] * 4), [0, 1, 2, 3], options, scale=1.0)

    def errors(p: np.ndarray) -> tuple[float, float]:
        rot = float(rotation_angle_deg(p[:, :3].T @ poses[2][:, :3]))
        return rot, float(np.linalg.norm(p[:, 3] - poses[2][:, 3]))

    rot0, trans0 = errors(perturbed[2])
    rot1, trans1 = errors(result.cam_from_world[2])
    assert rot1 < 0.3 * rot0 and trans1 < 0.3 * trans0, (rot0, rot1, trans0, trans1)
    assert np.array_equal(result.cam_from_world[0], perturbed[0])  # the gauge camera stays put
    assert torch.equal(result.gaussians.means, truth.means)  # frozen


def test_densifier_clones_splits_and_prunes():
    n = 6
    g = Gaussians.from_points(
        np.zeros((n, 3)), np.full((n, 3), 0.5), np.log([0.001, 0.001, 0.5, 0.5, 0.001, 0.001]), opacity=0.5
    )
    g.opacity_logits[5] = -8.0  # prune: opacity < 0.005
    d = Densifier(n, DensifyOptions(grad_threshold=0.01), scene_scale=1.0, max_gaussians=100, seed=0)
    grad = torch.zeros(n, 2)
    grad[[0, 2], 0] = 1.0  # hot: 0 is small (clone), 2 is large (split)
    d.accumulate(grad, torch.ones(n, dtype=torch.bool), width=2, height=2)
    new, keep, num_new = d.step(g)
    assert keep.tolist() == [True, True, False, True, True, False]
    assert num_new == 3 and len(new) == 4 + 3  # 0 cloned once, 2 replaced by two samples
    assert torch.allclose(new.log_scales[-1], torch.full((3,), float(np.log(0.5) - np.log(1.6))))


def test_replace_rows_carries_the_adam_moments_of_kept_rows():
    means = torch.zeros(6, 3, requires_grad=True)
    pose = torch.zeros(4, 3, requires_grad=True)
    adam = torch.optim.Adam([{"params": [means], "lr": 0.1, "name": "means"}, {"params": [pose], "name": "pose"}])
    for _ in range(2):
        means.grad = torch.arange(6.0)[:, None].expand(6, 3).clone()
        pose.grad = torch.ones(4, 3)
        adam.step()
    before = {k: v.clone() for k, v in adam.state[means].items()}
    pose_state = adam.state[pose]
    keep = torch.tensor([True, True, False, True, True, False])
    new = torch.ones(7, 3, requires_grad=True)
    replace_rows(adam, {"means": new}, keep, num_new=3)
    assert adam.param_groups[0]["params"] == [new] and means not in adam.state
    state = adam.state[new]
    for key in ("exp_avg", "exp_avg_sq"):
        assert state[key].shape == (7, 3)
        assert torch.equal(state[key][:4], before[key][keep]) and float(state[key][4:].abs().max()) == 0.0
    assert float(state["step"]) == 2.0
    assert adam.param_groups[1]["params"] == [pose] and adam.state[pose] is pose_state  # not resized
    new.grad = torch.ones(7, 3)
    adam.step()  # the optimiser goes on with the new tensor
    assert float(adam.state[new]["step"]) == 3.0 and bool((new < 1).all())
    with pytest.raises(ValueError):
        replace_rows(adam, {"means": torch.zeros(5, 3, requires_grad=True)}, torch.ones(7, dtype=torch.bool), 1)


def test_ssim_map_matches_kornia_inside_the_border():
    import kornia

    gen = torch.Generator().manual_seed(0)
    a, b = torch.rand(3, 40, 50, generator=gen), torch.rand(3, 40, 50, generator=gen)
    b = 0.5 * a + 0.5 * b
    ours = ssim_map(a, b)[:, 5:-5, 5:-5]
    ref = kornia.metrics.ssim(a[None], b[None], 11)[0][:, 5:-5, 5:-5]
    assert torch.allclose(ours, ref, atol=1e-4)


def test_fused_ssim_mean_and_gradient_match_autograd_of_the_map():
    from ffrecon.splat.ssim import ssim_mean

    gen = torch.Generator().manual_seed(1)
    a = torch.rand(3, 37, 45, generator=gen, requires_grad=True)
    b = 0.6 * a.detach() + 0.4 * torch.rand(3, 37, 45, generator=gen)
    ref = ssim_map(a, b).mean()
    ref.backward()
    expected, a.grad = a.grad.clone(), None
    ours = ssim_mean(a, b)
    ours.backward()
    assert abs(float(ours) - float(ref)) < 1e-6
    assert torch.allclose(a.grad, expected, rtol=1e-4, atol=1e-4 * float(expected.abs().max()))


def test_downscaled_views_keep_the_pixel_centre_rule():
    """A render at half resolution with the halved intrinsics equals the full render area-averaged."""
    truth = _truth(np.random.default_rng(3), n=600)
    poses = _cameras(2)
    full = _images(truth, poses)
    k_mats = torch.tensor(np.stack([K] * 2), dtype=torch.float32)
    small, small_k = downscaled(full, k_mats, 2, [0, 1])
    assert small[0].shape == (H // 2, W // 2, 3)
    assert torch.allclose(small_k[0, :2], k_mats[0, :2] / 2)

    def render_small(k: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            g = truth
            pose = torch.tensor(poses[0], dtype=torch.float32)
            args = (g.means, g.quats_wxyz, g.log_scales, g.opacity_logits, g.sh, pose, k, W // 2, H // 2)
            return render(*args, sh_degree=0).rgb

    shifted = small_k[0].clone()
    shifted[:2, 2] -= 0.25  # what the other pixel-centre rule (centre of the top-left pixel at 0) would give
    right, wrong = _psnr(render_small(small_k[0]), small[0]), _psnr(render_small(shifted), small[0])
    assert right > 25.0 and right > wrong + 1.0, (right, wrong)
    assert (
        resolution_factor(OptimizeOptions.brief(), 0.05) == 4 and resolution_factor(OptimizeOptions.brief(), 0.5) == 1
    )


def test_training_stops_on_a_loss_plateau_or_its_plan():
    rng = np.random.default_rng(4)
    truth = _truth(rng)
    poses = _cameras(5)
    images = _images(truth, poses)
    seed = truth.detached()  # already the answer: the loss is flat from the start
    base = OptimizeOptions(sh_degree=0, densify=None, progress=False, max_seconds=1e9)
    options = replace(
        base, iterations=2000, resolution_schedule=((0.0, 2), (0.01, 1)), plateau_window=25, plateau_after=0.02
    )
    result = optimize(seed, images, poses, np.stack([K] * 5), [0, 1, 2, 3, 4], options, scale=1.0)
    assert result.stop_reason == "plateau" and result.iterations < 200, (result.stop_reason, result.iterations)
    result = optimize(seed, images, poses, np.stack([K] * 5), [0, 1, 2, 3, 4], replace(base, iterations=30), scale=1.0)
    assert result.stop_reason == "iterations" and result.iterations == 30
