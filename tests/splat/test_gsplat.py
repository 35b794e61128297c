"""The CUDA path (gsplat) renders what the CPU renderer renders, gives the same gradients (Gaussians and
camera pose), and drives the splat's pose refinement (issue 21) as the CPU path does. Skipped without CUDA
and gsplat.

These tests import neither open3d nor the splat stage, so they also run where only torch, kornia and
gsplat are installed (the GPU check in docs/benchmarks.md ran them so).

Tolerance: max |difference| <= 2e-3 and mean <= 2e-4 per channel. The renderers follow the same
rules except that gsplat stops compositing a pixel once its transmittance falls below 1e-4
(differences up to ~1e-4) and computes in a different order on the GPU; opacities are kept <= 0.35
so that gsplat versions that cull at 3 sigma (where alpha <= 0.35 exp(-4.5) < 1/255) cull nothing
the CPU renderer would draw.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ffrecon.gaussians import Gaussians
from ffrecon.splat.poses import refined_pose
from ffrecon.splat.render import render, render_view
from ffrecon.splat.render_gsplat import gsplat_available, render_gsplat, render_view_on
from ffrecon.synthetic import SceneOptions, make_scene
from ffrecon.types import PinholeCamera

from .reference import check_turned_view_comes_back, random_scene

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not gsplat_available(), reason="needs CUDA and gsplat (ffrecon[gpu])"),
]


@pytest.mark.parametrize("sh_degree", [None, 2])
def test_gsplat_matches_cpu_renderer(sh_degree):
    rng = np.random.default_rng(0)
    w, h = 128, 96
    scene = random_scene(rng, 300, w, h, sh_bases=1 if sh_degree is None else 9)
    scene["opacity_logits"] = np.clip(scene["opacity_logits"], -4.0, np.log(0.35 / 0.65))
    pose = torch.eye(4)[:3]
    bg = torch.tensor([0.1, 0.2, 0.3])
    cpu = {k: torch.tensor(v, dtype=torch.float32, requires_grad=k == "means") for k, v in scene.items()}
    gpu = {k: torch.tensor(v, dtype=torch.float32, device="cuda", requires_grad=k == "means") for k, v in scene.items()}
    a = render(
        cpu["means"],
        cpu["quats_wxyz"],
        cpu["log_scales"],
        cpu["opacity_logits"],
        cpu["colors"],
        pose,
        cpu["K"],
        w,
        h,
        background=bg,
        sh_degree=sh_degree,
    )
    b = render_gsplat(
        gpu["means"],
        gpu["quats_wxyz"],
        gpu["log_scales"],
        gpu["opacity_logits"],
        gpu["colors"],
        pose.cuda(),
        gpu["K"],
        w,
        h,
        background=bg.cuda(),
        sh_degree=sh_degree,
    )
    diff = (a.rgb - b.rgb.cpu()).abs()
    assert float(diff.max()) <= 2e-3 and float(diff.mean()) <= 2e-4
    assert float((a.alpha - b.alpha.cpu()).abs().max()) <= 2e-3
    weights = torch.rand(h, w, 3, generator=torch.Generator().manual_seed(1))
    (a.rgb * weights).sum().backward()
    (b.rgb * weights.cuda()).sum().backward()
    ga, gb = cpu["means"].grad.flatten(), gpu["means"].grad.cpu().flatten()
    assert float(torch.nn.functional.cosine_similarity(ga, gb, dim=0)) > 0.99


def _low_opacity_scene(seed: int) -> dict:
    scene = random_scene(np.random.default_rng(seed), 300, 128, 96)
    scene["opacity_logits"] = np.clip(scene["opacity_logits"], -4.0, np.log(0.35 / 0.65))
    return scene


def test_render_view_on_cuda_matches_the_cpu_render_view():
    """What the held-out scores, report renders and fly-through use: same image on either device."""
    scene = _low_opacity_scene(2)
    g = Gaussians.from_points(scene["means"], scene["colors"], scene["log_scales"], opacity=0.3, sh_degree=1)
    g.sh[:, 1:] = torch.tensor(np.random.default_rng(3).normal(0, 0.2, (len(g), 3, 3)), dtype=torch.float32)
    camera = PinholeCamera.from_K(scene["K"], 128, 96)
    pose = np.eye(4)[:3]
    cpu = render_view(g, pose, camera, background=(0.1, 0.2, 0.3))
    cuda = render_view_on("cuda", g, pose, camera, background=(0.1, 0.2, 0.3))
    assert cuda.device.type == "cpu" and cuda.shape == cpu.shape == (96, 128, 3)
    diff = (cpu - cuda).abs()
    # max: one 8-bit level. A Gaussian whose alpha at a pixel sits on the 1/255 cut may be drawn by one
    # renderer and not the other (float32 in a different order): at most alpha * colour < 1/255 there.
    # Measured on an H100: 2.15e-3 here, 1.7e-3 to 2.2e-3 in tools/bench_view_render.py.
    assert float(diff.max()) <= 1 / 255 and float(diff.mean()) <= 2e-4


def test_pose_gradients_match_the_cpu_renderer():
    """The gradient of a photometric loss with respect to a view's pose correction (rotation, translation):
    cosine similarity > 0.99 between gsplat and the CPU renderer."""
    scene = _low_opacity_scene(4)
    w, h = 128, 96
    target_pose = refined_pose(torch.eye(4)[:3], torch.tensor([0.01, -0.02, 0.005]), torch.tensor([0.02, 0.0, -0.01]))
    grads = []
    for device, fn in (("cpu", render), ("cuda", render_gsplat)):
        t = {k: torch.tensor(v, dtype=torch.float32, device=device) for k, v in scene.items()}
        args = (t["means"], t["quats_wxyz"], t["log_scales"], t["opacity_logits"], t["colors"])

        def draw(pose, fn=fn, args=args, t=t, device=device):
            return fn(*args, pose.to(device), t["K"], w, h, background=torch.zeros(3, device=device)).rgb

        with torch.no_grad():
            target = draw(target_pose)
        rotation = torch.zeros(3, device=device, requires_grad=True)
        translation = torch.zeros(3, device=device, requires_grad=True)
        loss = (draw(refined_pose(torch.eye(4, device=device)[:3], rotation, translation)) - target).abs().mean()
        loss.backward()
        grads.append(torch.cat([rotation.grad, translation.grad]).cpu())
    assert float(grads[0].norm()) > 0
    assert float(torch.nn.functional.cosine_similarity(grads[0], grads[1], dim=0)) > 0.99, grads


def test_a_wrong_camera_moves_towards_the_truth_on_gsplat():
    """tests/splat/test_pose_refinement.py's check, trained with gsplat: view 3 turned 2 deg comes back
    within 1 deg and every other camera is returned as given. The seed is built here (exact points, one
    pixel's footprint wide) instead of by ffrecon.splat.seed, which needs open3d."""
    scene = make_scene(SceneOptions(num_frames=9, width=96, height=72))
    train = range(1, len(scene))
    xyz = np.concatenate([scene.frame_points(i).reshape(-1, 3) for i in train])
    rgb = np.concatenate([scene.images[i].reshape(-1, 3) for i in train]).astype(np.float32) / 255.0
    footprint = np.concatenate([scene.depth[i].reshape(-1) for i in train]) / scene.camera.K[0, 0]
    keep = np.random.default_rng(0).choice(len(xyz), 20_000, replace=False)
    seed = Gaussians.from_points(xyz[keep], rgb[keep], np.log(footprint[keep]))
    check_turned_view_comes_back(scene, seed, xyz, device="cuda")
