"""The CPU splat renderer against a brute-force per-pixel reference, and its gradients against
central finite differences (float64)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from kornia.geometry.liegroup import So3

from ffrecon.gaussians import SH_C0, SH_C1, sh_basis, sh_to_rgb
from ffrecon.geometry.rotations import random_rotation
from ffrecon.splat.render import RasterOptions, render

from .reference import random_scene, reference_render

W, H = 61, 47


def _pose(rng: np.random.Generator, scene: dict, angle_deg: float) -> np.ndarray:
    """A camera moved slightly off the identity, and the scene moved with it (same image content)."""
    rot = np.eye(3)
    if angle_deg:
        axis = rng.normal(size=3)
        rot = So3.exp(torch.tensor(axis / np.linalg.norm(axis) * np.radians(angle_deg))).matrix().numpy()
    world_from_cam_rot = random_rotation(rng)
    center = rng.normal(size=3)
    # x_cam = rot @ world_from_cam_rot^T (x_world - center): the scene is placed so it stays in view.
    cam_from_world = np.concatenate(
        [rot @ world_from_cam_rot.T, (-rot @ world_from_cam_rot.T @ center)[:, None]], axis=1
    )
    scene["means"] = scene["means"] @ world_from_cam_rot.T + center
    return cam_from_world


def _torch(scene: dict, dtype=torch.float32) -> dict:
    return {k: torch.tensor(v, dtype=dtype) for k, v in scene.items()}


@pytest.mark.parametrize("tile_size, seed", [(8, 0), (16, 1), (4, 2)])
def test_matches_brute_force_reference(tile_size, seed):
    rng = np.random.default_rng(seed)
    scene = random_scene(rng, 60, W, H)
    scene["opacity_logits"][:5] = 8.0  # some alphas hit the 0.999 clamp
    scene["means"][5, 2] = -1.0  # one behind the camera
    scene["means"][6, :2] = scene["means"][6, 2] * 1.5  # one far outside the image
    pose = _pose(rng, scene, angle_deg=3.0)
    bg = np.array([0.2, 0.5, 0.9])
    ref_rgb, ref_alpha, ref_depth = reference_render(
        scene["means"],
        scene["quats_wxyz"],
        scene["log_scales"],
        scene["opacity_logits"],
        scene["colors"],
        pose,
        scene["K"],
        W,
        H,
        bg,
    )
    t = _torch(scene)
    out = render(
        t["means"],
        t["quats_wxyz"],
        t["log_scales"],
        t["opacity_logits"],
        t["colors"],
        torch.tensor(pose, dtype=torch.float32),
        t["K"],
        W,
        H,
        background=torch.tensor(bg, dtype=torch.float32),
        options=RasterOptions(tile_size=tile_size),
    )
    assert ref_alpha.max() > 0.95 and ref_alpha.min() < 0.5  # a scene with both opaque and empty parts
    assert np.abs(out.rgb.numpy() - ref_rgb).max() < 1e-4
    assert np.abs(out.alpha.numpy() - ref_alpha).max() < 1e-4
    assert np.abs(out.depth.numpy() - ref_depth).max() < 1e-4 * ref_depth.max()


def test_tile_size_does_not_change_the_image():
    rng = np.random.default_rng(3)
    t = _torch(random_scene(rng, 80, W, H))
    pose = torch.eye(4)[:3]
    imgs = [
        render(
            t["means"],
            t["quats_wxyz"],
            t["log_scales"],
            t["opacity_logits"],
            t["colors"],
            pose,
            t["K"],
            W,
            H,
            options=RasterOptions(tile_size=ts),
        ).rgb
        for ts in (8, 4, 16)
    ]
    assert torch.allclose(imgs[0], imgs[1], atol=1e-5) and torch.allclose(imgs[0], imgs[2], atol=1e-5)


def test_nothing_visible_gives_background():
    rng = np.random.default_rng(4)
    t = _torch(random_scene(rng, 10, W, H))
    t["means"][:, 2] = -t["means"][:, 2]  # all behind the camera
    bg = torch.tensor([0.1, 0.2, 0.3])
    out = render(
        t["means"],
        t["quats_wxyz"],
        t["log_scales"],
        t["opacity_logits"],
        t["colors"],
        torch.eye(4)[:3],
        t["K"],
        W,
        H,
        background=bg,
    )
    assert torch.equal(out.rgb, bg.expand(H, W, 3)) and float(out.alpha.abs().max()) == 0.0 and not out.visible.any()


def _fd_check(
    scene: dict,
    rng: np.random.Generator,
    *,
    sh_degree: int | None,
    width: int,
    height: int,
    samples_per_tensor: int = 12,
) -> None:
    """Autograd gradients of a random linear function of (rgb, alpha, depth) vs central differences."""
    d = torch.float64
    params = {k: torch.tensor(v, dtype=d, requires_grad=True) for k, v in scene.items() if k != "K"}
    params["pose"] = torch.tensor(rng.normal(scale=0.02, size=6), dtype=d, requires_grad=True)  # so(3) and translation
    params["background"] = torch.tensor([0.3, 0.1, 0.7], dtype=d, requires_grad=True)
    K = torch.tensor(scene["K"], dtype=d)
    weights = [
        torch.tensor(rng.normal(size=s), dtype=d) for s in ((height, width, 3), (height, width), (height, width))
    ]

    def loss_fn() -> torch.Tensor:
        rot = So3.exp(params["pose"][:3]).matrix()
        pose = torch.cat([rot, params["pose"][3:, None]], dim=1)
        out = render(
            params["means"],
            params["quats_wxyz"],
            params["log_scales"],
            params["opacity_logits"],
            params["colors"],
            pose,
            K,
            width,
            height,
            background=params["background"],
            sh_degree=sh_degree,
            options=RasterOptions(tile_size=8),
        )
        return (out.rgb * weights[0]).sum() + (out.alpha * weights[1]).sum() + (out.depth * weights[2]).sum()

    loss_fn().backward()
    eps = 1e-6
    for name, x in params.items():
        flat = x.data.view(-1)
        picks = rng.choice(flat.numel(), min(samples_per_tensor, flat.numel()), replace=False)
        analytic = x.grad.view(-1)[picks].numpy()
        numeric = []
        with torch.no_grad():
            for i in picks:
                old = float(flat[i])
                flat[i] = old + eps
                plus = float(loss_fn())
                flat[i] = old - eps
                minus = float(loss_fn())
                flat[i] = old
                numeric.append((plus - minus) / (2 * eps))
        numeric = np.array(numeric)
        scale = max(np.abs(numeric).max(), 1e-3)
        assert np.abs(analytic - numeric).max() < 1e-5 * scale, (name, analytic, numeric)


def test_gradients_match_finite_differences():
    rng = np.random.default_rng(5)
    _fd_check(random_scene(rng, 14, 37, 29), rng, sh_degree=None, width=37, height=29)


def test_gradients_with_sh_and_clamped_alphas():
    rng = np.random.default_rng(6)
    scene = random_scene(rng, 10, 37, 29, sh_bases=4)
    scene["opacity_logits"][:3] = 7.5  # sigmoid > 0.999: the centres clamp, the rest does not
    _fd_check(scene, rng, sh_degree=1, width=37, height=29)


def test_sh_basis_is_orthonormal_and_has_3dgs_signs():
    dirs = torch.nn.functional.normalize(
        torch.randn(400_000, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64), dim=1
    )
    basis = sh_basis(dirs, 3)  # [M, 16]
    gram = 4 * np.pi * (basis.T @ basis).numpy() / len(dirs)  # integral over the sphere of Y_i Y_j
    assert np.abs(gram - np.eye(16)).max() < 0.02
    y_axis = sh_basis(torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64), 1)[0]
    assert np.allclose(y_axis.numpy(), [SH_C0, -SH_C1, 0.0, 0.0])  # 3DGS: band 1 is (-y, z, -x)
    sh = torch.zeros(1, 4, 3, dtype=torch.float64)
    sh[0, 0] = torch.tensor([1.0, -3.0, 0.0])  # green goes negative: clamped to 0
    sh[0, 2] = torch.tensor([0.0, 0.0, 0.5])  # the z coefficient of band 1
    rgb = sh_to_rgb(sh, y_axis.new_tensor([[0.0, 0.0, 1.0]]), 1).numpy()
    assert np.allclose(rgb, [[0.5 + SH_C0, 0.0, 0.5 + 0.5 * SH_C1]])
    assert np.allclose(
        sh_to_rgb(sh, y_axis.new_tensor([[0.0, 0.0, 1.0]]), 0).numpy(), [[0.5 + SH_C0, 0.0, 0.5]]
    )  # band 1 off


def test_ctrl_c_during_kernel_compilation_is_held_until_it_is_done():
    """A SIGINT while numba compiles must not be swallowed by LLVM's callback (a half-built kernel hung the
    process): it is held, and raised as KeyboardInterrupt once the block ends."""
    import os
    import signal

    from ffrecon.splat.render import interrupts_deferred

    before = signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal (CI may ignore SIGINT)
    try:
        finished = False
        with pytest.raises(KeyboardInterrupt):
            with interrupts_deferred():
                os.kill(os.getpid(), signal.SIGINT)
                finished = True
        assert finished and signal.getsignal(signal.SIGINT) is signal.default_int_handler
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # an ignored SIGINT stays ignored
        with interrupts_deferred():
            os.kill(os.getpid(), signal.SIGINT)
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, before)
