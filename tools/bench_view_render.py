"""Time one plain render of a finished splat (held-out scores, report renders, the fly-through's frames)
on the CPU renderer and, where CUDA and gsplat are present, on gsplat, in the same run.

Usage (from the repository root):

    .venv/bin/python tools/bench_view_render.py                       # 100k and 500k Gaussians, 640x480
    .venv/bin/python tools/bench_view_render.py --gaussians 1000000 --size 1280 960 --repeats 5

The scene: random anisotropic Gaussians (SH degree 3, opacities 0.05-0.6) filling the view of an identity
camera at depths 2-6. Each device renders ``--repeats`` frames after three warm-up renders (numba's compile,
gsplat's first call, the GPU's clocks); the median is printed, with the largest per-channel difference between the two
images (gsplat stops compositing a pixel at transmittance 1e-4, the CPU renderer does not). Needs neither
open3d nor pycolmap.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from ffrecon.gaussians import Gaussians
from ffrecon.splat.render_gsplat import gsplat_available, render_view_on
from ffrecon.types import PinholeCamera


def random_splat(n: int, camera: PinholeCamera, seed: int = 0) -> Gaussians:
    rng = np.random.default_rng(seed)
    z = rng.uniform(2.0, 6.0, n)
    half = np.array([camera.width / camera.K[0, 0], camera.height / camera.K[1, 1]]) / 2
    xy = rng.uniform(-1.0, 1.0, (n, 2)) * half * z[:, None]
    xyz = np.concatenate([xy, z[:, None]], 1)
    log_scales = np.log(rng.uniform(0.2, 2.0, (n, 3)) * z[:, None] / camera.K[0, 0] * 3)
    g = Gaussians.from_points(xyz, rng.uniform(0, 1, (n, 3)), log_scales, sh_degree=3)
    g.quats_wxyz = torch.tensor(rng.normal(size=(n, 4)), dtype=torch.float32)
    opacity = rng.uniform(0.05, 0.6, n)
    g.opacity_logits = torch.tensor(np.log(opacity / (1 - opacity)), dtype=torch.float32)
    g.sh[:, 1:] = torch.tensor(rng.normal(0, 0.1, (n, 15, 3)), dtype=torch.float32)
    return g


def time_renders(device: str, g: Gaussians, camera: PinholeCamera, repeats: int) -> tuple[float, torch.Tensor]:
    """Median seconds per render after three warm-up renders, and the last image."""
    g = g.to(device)
    pose = np.eye(4)[:3]
    for _ in range(3):  # warm-up: numba's compile, gsplat's first call, the GPU's clocks
        image = render_view_on(device, g, pose, camera)
    seconds = []
    for _ in range(repeats):
        start = time.perf_counter()
        image = render_view_on(device, g, pose, camera)
        seconds.append(time.perf_counter() - start)
    return float(np.median(seconds)), image


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--gaussians", type=int, nargs="+", default=[100_000, 500_000])
    parser.add_argument("--size", type=int, nargs=2, default=[640, 480], metavar=("W", "H"))
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    w, h = args.size
    camera = PinholeCamera.from_K(np.array([[0.9 * w, 0, w / 2], [0, 0.9 * w, h / 2], [0, 0, 1.0]]), w, h)
    devices = ["cpu", "cuda"] if gsplat_available() else ["cpu"]
    print(f"{w}x{h}, torch threads {torch.get_num_threads()}, devices {devices}")
    for n in args.gaussians:
        g = random_splat(n, camera)
        results = {d: time_renders(d, g, camera, args.repeats) for d in devices}
        line = f"{n:>9,d} Gaussians: cpu {results['cpu'][0] * 1e3:8.1f} ms"
        if "cuda" in results:
            diff = float((results["cpu"][1] - results["cuda"][1]).abs().max())
            ratio = results["cpu"][0] / results["cuda"][0]
            line += f", gsplat {results['cuda'][0] * 1e3:7.1f} ms, cpu / gsplat {ratio:6.1f}x"
            line += f", max |difference| {diff:.1e}"
        print(line, flush=True)


if __name__ == "__main__":
    main()
