"""Benchmark the CPU splat: renderer speed, and held-out PSNR against optimisation time.

Usage (from the repository root):

    .venv/bin/python tools/bench_splat.py                  # both parts, demo-sized scene, 120 s budget
    .venv/bin/python tools/bench_splat.py --render-only
    .venv/bin/python tools/bench_splat.py --seconds 60 --eval-every 50 --threads 1

The scene is the demo's synthetic one (24 views at 320x240, every 8th held out). Seeds come from the
simulated model's depth maps (a smooth ~3 % error field, as the demo's simulated VGGT) unprojected
with the ground-truth cameras of the training views. Timings on a shared machine are pessimistic:
other processes take cores, and the numbers say how busy the machine was (load average).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from dataclasses import replace

import numpy as np
import torch

from ffrecon.geometry.projection import unproject_depth
from ffrecon.splat.optimize import cpu_threads, optimize, scene_scale, torch_threads
from ffrecon.splat.render import RasterOptions, render, render_view
from ffrecon.splat.seed import initial_gaussians, reduce_points
from ffrecon.splat.stage import SplatOptions, image_metrics, split_views
from ffrecon.synthetic import SceneOptions, make_scene
from ffrecon.synthetic.simulated_model import SimulationOptions, simulate


def noisy_seed(scene, views: list[int], seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points of ``views`` from the simulated model's noisy depth at the true cameras, with colours."""
    truth, _ = simulate(scene, SimulationOptions(seed=seed))
    xyz = np.concatenate(
        [unproject_depth(truth.depth[i], scene.camera.K, scene.cam_from_world[i]).reshape(-1, 3) for i in views]
    )
    rgb = np.concatenate([scene.images[i].reshape(-1, 3) for i in views]).astype(np.float32) / 255.0
    return xyz, rgb


def bench_render(xyz: np.ndarray, rgb: np.ndarray, scene, counts: list[int], raster: RasterOptions) -> None:
    K = torch.tensor(scene.camera.K, dtype=torch.float32)
    w, h = scene.camera.width, scene.camera.height
    threads = torch.get_num_threads()
    print(
        f"\nrenderer, {w}x{h}, tile {raster.tile_size}, {threads} thread(s): forward and forward+backward, median of 5"
    )
    print(f"{'gaussians':>10} {'pairs':>9} {'evals/px':>9} {'fwd ms':>8} {'fwd+bwd ms':>11} {'it/s':>6}")
    for n in counts:
        x, c = reduce_points(xyz, rgb, voxel_size=None, max_points=n)
        g = initial_gaussians(x, c, sh_degree=0)
        params = [g.means, g.quats_wxyz, g.log_scales, g.opacity_logits, g.sh]
        for p in params:
            p.requires_grad_(True)
        fwd, full = [], []
        for it in range(6):
            pose = torch.tensor(scene.cam_from_world[it % len(scene)], dtype=torch.float32)
            t0 = time.perf_counter()
            out = render(*params, pose, K, w, h, sh_degree=0, with_depth=False, options=raster)
            loss = out.rgb.mean()
            t1 = time.perf_counter()
            loss.backward()
            t2 = time.perf_counter()
            if it:
                fwd.append(t1 - t0)
                full.append(t2 - t0)
        med = float(np.median(full))
        evals = out.layout.padded_evaluations / (w * h)
        print(
            f"{len(x):>10} {out.layout.num_pairs:>9} {evals:>9.0f} {1e3 * np.median(fwd):>8.0f} "
            f"{1e3 * med:>11.0f} {1 / med:>6.2f}"
        )


def heldout_psnr(g, scene, poses: np.ndarray, test: list[int]) -> float:
    """Mean PSNR of ``g`` over the views ``test`` of ``scene`` seen from ``poses``."""
    values = []
    for i in test:
        rendered = render_view(g, poses[i], scene.camera)
        values.append(image_metrics(rendered, torch.from_numpy(scene.images[i]).float() / 255.0)[0])
    return float(np.mean(values))


def bench_optimize(scene, xyz, rgb, train, test, args) -> None:
    options = SplatOptions()
    opt = replace(options.optimize, max_seconds=args.seconds, progress=False, threads=args.threads)
    x, c = reduce_points(xyz, rgb, voxel_size=None, max_points=min(options.max_seed_points, opt.max_gaussians), seed=0)
    seed = initial_gaussians(x, c, sh_degree=opt.sh_degree)
    targets = [torch.from_numpy(im).float() / 255.0 for im in scene.images]
    Ks = np.stack([scene.camera.K] * len(scene))
    print(
        f"\noptimisation: {len(train)} training / {len(test)} held-out views, seed {len(seed)} Gaussians, "
        f"budget {args.seconds:.0f} s, {torch.get_num_threads()} thread(s); evaluation time excluded"
    )
    print(f"{'iteration':>9} {'seconds':>8} {'it/s':>6} {'gaussians':>10} {'held-out PSNR':>14}")
    print(f"{0:>9} {0.0:>8.1f} {'':>6} {len(seed):>10} {heldout_psnr(seed, scene, scene.cam_from_world, test):>14.2f}")

    def callback(it, seconds, g, poses):
        psnr = heldout_psnr(g, scene, poses, test)
        print(f"{it:>9} {seconds:>8.1f} {it / seconds:>6.2f} {len(g):>10} {psnr:>14.2f}", flush=True)

    scale = scene_scale(scene.cam_from_world[train], x)
    result = optimize(
        seed,
        targets,
        scene.cam_from_world,
        Ks,
        train,
        opt,
        scale=scale,
        callback=callback,
        callback_every=args.eval_every,
    )
    psnr = heldout_psnr(result.gaussians, scene, result.cam_from_world, test)
    rate = result.iterations / result.seconds
    count = len(result.gaussians)
    print(f"{result.iterations:>9} {result.seconds:>8.1f} {rate:>6.2f} {count:>10} {psnr:>14.2f}   (final)")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--seconds", type=float, default=120.0)
    parser.add_argument("--eval-every", type=int, default=50, help="iterations between held-out evaluations")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: all cores but one)")
    parser.add_argument("--counts", default="30000,60000,100000", help="Gaussian counts for the renderer benchmark")
    parser.add_argument(
        "--tile", type=int, default=RasterOptions().tile_size, help="tile size of the renderer benchmark"
    )
    parser.add_argument("--render-only", action="store_true")
    parser.add_argument("--optimize-only", action="store_true")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"torch {torch.__version__}, {os.cpu_count()} CPUs, load average {load:.2f} at start")
    scene = make_scene(SceneOptions(num_frames=args.frames))
    train, test = split_views(len(scene), SplatOptions().holdout_every)
    xyz, rgb = noisy_seed(scene, train)
    with torch_threads(cpu_threads(args.threads)):
        if not args.optimize_only:
            bench_render(xyz, rgb, scene, [int(c) for c in args.counts.split(",")], RasterOptions(tile_size=args.tile))
        if not args.render_only:
            bench_optimize(scene, xyz, rgb, train, test, args)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"load average {load:.2f} at the end")
    return 0


if __name__ == "__main__":
    sys.exit(main())
