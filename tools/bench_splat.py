"""Benchmark the CPU splat: renderer speed, and held-out PSNR against optimisation time.

Usage (from the repository root):

    .venv/bin/python tools/bench_splat.py                  # both parts, demo-sized scene, 120 s budget
    .venv/bin/python tools/bench_splat.py --render-only
    .venv/bin/python tools/bench_splat.py --seconds 60 --eval-every 50 --threads 1
    # exposure compensation off and on, a fixed budget of 300 iterations, constant or varying exposure:
    .venv/bin/python tools/bench_splat.py --optimize-only --iterations 300 --seconds 1e9 --appearance both
    .venv/bin/python tools/bench_splat.py --optimize-only --iterations 300 --seconds 1e9 --appearance both \
        --exposure 0.3
    .venv/bin/python tools/bench_splat.py --memory        # peak memory of a step against ffrecon.splat.memory

``--memory`` runs, in a fresh process per size, three full-resolution optimisation steps on two views
of random pixels and 200k Gaussians, at 1600x1200 to 6400x4800, and prints how much the peak resident
memory grew against the estimate of :mod:`ffrecon.splat.memory` (the constants there were fitted so).

The scene is the demo's synthetic one (24 views at 320x240, every 8th held out). Seeds come from the
simulated model's depth maps (a smooth ~3 % error field, as the demo's simulated VGGT) unprojected
with the ground-truth cameras of the training views. ``--exposure g`` changes every photo's colours
(training and held-out) as auto-exposure and white balance would: per-channel gains in [1 - g, 1 + g]
and offsets within g / 10, seeded (see :func:`ffrecon.splat.appearance.random_color_changes`).
Held-out PSNR is printed plain and colour-corrected (see :func:`ffrecon.splat.stage.color_corrected`).
Timings on a shared machine are pessimistic: other processes take cores, and the numbers say how
busy the machine was (load average).
"""

from __future__ import annotations

import argparse
import logging
import os
import resource
import subprocess
import sys
import time
from dataclasses import replace

import numpy as np
import torch

from ffrecon.geometry.projection import unproject_depth
from ffrecon.splat.appearance import change_photo_colors, random_color_changes
from ffrecon.splat.optimize import cpu_threads, optimize, scene_scale, torch_threads
from ffrecon.splat.raster import kernel_threads, raster_threads
from ffrecon.splat.render import RasterOptions, render, render_view
from ffrecon.splat.seed import initial_gaussians, reduce_points
from ffrecon.splat.stage import SplatOptions, color_corrected, image_metrics, split_views
from ffrecon.synthetic import SceneOptions, make_scene
from ffrecon.synthetic.simulated_model import SimulationOptions, simulate


def noisy_seed(scene, images, views: list[int], seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points of ``views`` from the simulated model's noisy depth at the true cameras, with the colours of
    ``images`` (per frame ``[H, W, 3]`` uint8)."""
    truth, _ = simulate(scene, SimulationOptions(seed=seed))
    xyz = np.concatenate(
        [unproject_depth(truth.depth[i], scene.camera.K, scene.cam_from_world[i]).reshape(-1, 3) for i in views]
    )
    rgb = np.concatenate([images[i].reshape(-1, 3) for i in views]).astype(np.float32) / 255.0
    return xyz, rgb


def bench_render(xyz: np.ndarray, rgb: np.ndarray, scene, counts: list[int], raster: RasterOptions) -> None:
    """Forward and forward+backward times of the renderer at the seed's Gaussians (median of 5 views),
    with the compiled kernels on 1 thread and on every core (torch itself on 1 thread)."""
    K = torch.tensor(scene.camera.K, dtype=torch.float32)
    w, h = scene.camera.width, scene.camera.height
    print(f"\nrenderer, {w}x{h}, tile {raster.tile_size}: forward and forward+backward, median of 5 views")
    print(f"{'gaussians':>10} {'pairs':>9} {'pairs/px':>9} {'threads':>8} {'fwd ms':>8} {'fwd+bwd ms':>11} {'it/s':>6}")
    for n in counts:
        x, c = reduce_points(xyz, rgb, voxel_size=None, max_points=n)
        g = initial_gaussians(x, c, sh_degree=0)
        params = [g.means, g.quats_wxyz, g.log_scales, g.opacity_logits, g.sh]
        for p in params:
            p.requires_grad_(True)
        for threads in sorted({1, kernel_threads()}):
            with torch_threads(1), raster_threads(threads):
                fwd, full = [], []
                for it in range(6):
                    pose = torch.tensor(scene.cam_from_world[it % len(scene)], dtype=torch.float32)
                    t0 = time.perf_counter()
                    out = render(*params, pose, K, w, h, sh_degree=0, with_depth=False, options=raster)
                    loss = out.rgb.mean()
                    t1 = time.perf_counter()
                    loss.backward()
                    t2 = time.perf_counter()
                    if it:  # the first call compiles the kernels (or loads them from numba's cache)
                        fwd.append(t1 - t0)
                        full.append(t2 - t0)
            med = float(np.median(full))
            print(
                f"{len(x):>10} {out.layout.num_pairs:>9} {out.layout.num_pairs / (w * h):>9.2f} {threads:>8} "
                f"{1e3 * np.median(fwd):>8.1f} {1e3 * med:>11.1f} {1 / med:>6.1f}"
            )


def heldout_psnr(g, scene, images, poses: np.ndarray, test: list[int]) -> str:
    """Mean PSNR of ``g`` over the views ``test`` of ``scene`` seen from ``poses``, plain and colour-corrected
    against ``images`` (per frame ``[H, W, 3]`` uint8), formatted for the table."""
    plain, corrected = [], []
    for i in test:
        rendered = render_view(g, poses[i], scene.camera)
        truth = torch.from_numpy(images[i]).float() / 255.0
        plain.append(image_metrics(rendered, truth)[0])
        corrected.append(image_metrics(color_corrected(rendered, truth), truth)[0])
    return f"{np.mean(plain):>14.2f} {np.mean(corrected):>10.2f}"


def bench_optimize(scene, images, xyz, rgb, train, test, args, appearance: bool) -> None:
    options = SplatOptions()
    opt = replace(
        options.optimize,
        max_seconds=args.seconds,
        progress=False,
        threads=args.threads,
        appearance=appearance,
        **({"iterations": args.iterations} if args.iterations else {}),
    )
    x, c = reduce_points(xyz, rgb, voxel_size=None, max_points=min(options.max_seed_points, opt.max_gaussians), seed=0)
    seed = initial_gaussians(x, c, sh_degree=opt.sh_degree)
    targets = [torch.from_numpy(im).float() / 255.0 for im in images]
    Ks = np.stack([scene.camera.K] * len(scene))
    print(
        f"\noptimisation: {len(train)} training / {len(test)} held-out views, seed {len(seed)} Gaussians, "
        f"budget {opt.iterations} iterations or {args.seconds:.0f} s, {torch.get_num_threads()} thread(s), "
        f"exposure changes {args.exposure}, appearance compensation {'on' if appearance else 'off'}; "
        "evaluation time excluded"
    )
    print(f"{'iteration':>9} {'seconds':>8} {'it/s':>6} {'gaussians':>10} {'held-out PSNR':>14} {'corrected':>10}")
    print(f"{0:>9} {0.0:>8.1f} {'':>6} {len(seed):>10} {heldout_psnr(seed, scene, images, scene.cam_from_world, test)}")

    def callback(it, seconds, g, poses):
        psnr = heldout_psnr(g, scene, images, poses, test)
        print(f"{it:>9} {seconds:>8.1f} {it / seconds:>6.2f} {len(g):>10} {psnr}", flush=True)

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
    psnr = heldout_psnr(result.gaussians, scene, images, result.cam_from_world, test)
    rate = result.iterations / result.seconds
    count = len(result.gaussians)
    print(
        f"{result.iterations:>9} {result.seconds:>8.1f} {rate:>6.2f} {count:>10} {psnr}   (final: {result.stop_reason})"
    )


MEMORY_SIZES = ((1600, 1200), (3200, 2400), (4800, 3600), (6400, 4800))
MEMORY_GAUSSIANS = 200_000


def memory_probe(width: int, height: int, count: int) -> None:
    """One process's part of ``--memory``: prints the growth of its peak RSS over three steps, in bytes."""
    from ffrecon.gaussians import Gaussians

    rng = np.random.default_rng(0)
    xyz = np.c_[rng.uniform(-1, 1, (count, 2)), rng.uniform(2, 4, count)]
    g = Gaussians.from_points(xyz, rng.uniform(0, 1, (count, 3)), np.full(count, np.log(0.01)), opacity=0.5)
    k = np.array([[0.9 * width, 0, width / 2], [0, 0.9 * width, height / 2], [0, 0, 1]])
    images = [torch.rand(height, width, 3) for _ in range(2)]
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    options = replace(
        SplatOptions().optimize, iterations=3, max_seconds=1e9, progress=False, resolution_schedule=((0.0, 1),)
    )
    optimize(g, images, np.stack([np.eye(3, 4)] * 2), np.stack([k, k]), [0, 1], options, scale=1.0)
    print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 - base)


def bench_memory() -> None:
    from ffrecon.splat.memory import BASE_BYTES, splat_peak_bytes

    print(f"{'view':>10} {'measured growth':>16} {'estimate':>9}  (2 views, {MEMORY_GAUSSIANS} Gaussians)")
    for w, h in MEMORY_SIZES:
        probe = [sys.executable, __file__, "--memory-probe", str(w), str(h), str(MEMORY_GAUSSIANS)]
        grown = int(subprocess.run(probe, check=True, capture_output=True, text=True).stdout.split()[-1])
        estimate = splat_peak_bytes([(w, h)] * 2, MEMORY_GAUSSIANS) - BASE_BYTES
        print(f"{w}x{h:<5} {grown / 2**30:13.2f} GB {estimate / 2**30:6.2f} GB")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--seconds", type=float, default=120.0)
    parser.add_argument("--iterations", type=int, default=0, help="iteration budget (default: the options')")
    parser.add_argument("--appearance", choices=("on", "off", "both"), default="on", help="exposure compensation")
    parser.add_argument("--exposure", type=float, default=0.0, help="per-photo colour gain spread (0: constant)")
    parser.add_argument("--eval-every", type=int, default=50, help="iterations between held-out evaluations")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: all cores but one)")
    parser.add_argument("--counts", default="30000,60000,100000", help="Gaussian counts for the renderer benchmark")
    parser.add_argument(
        "--tile", type=int, default=RasterOptions().tile_size, help="tile size of the renderer benchmark"
    )
    parser.add_argument("--render-only", action="store_true")
    parser.add_argument("--optimize-only", action="store_true")
    parser.add_argument("--memory", action="store_true", help="peak memory of a step against the splat's estimate")
    parser.add_argument("--memory-probe", nargs=3, type=int, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.memory_probe:
        memory_probe(*args.memory_probe)
        return 0
    if args.memory:
        bench_memory()
        return 0
    logging.basicConfig(level=logging.WARNING)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"torch {torch.__version__}, {os.cpu_count()} CPUs, load average {load:.2f} at start")
    scene = make_scene(SceneOptions(num_frames=args.frames, width=args.width, height=args.height))
    train, test = split_views(len(scene), SplatOptions().holdout_every)
    images = list(scene.images)
    if args.exposure:
        changes = random_color_changes(len(scene), gain_spread=args.exposure, offset_spread=args.exposure / 10)
        images = [change_photo_colors(im, t) for im, t in zip(images, changes)]
    xyz, rgb = noisy_seed(scene, images, train)
    with torch_threads(cpu_threads(args.threads)):
        if not args.optimize_only:
            bench_render(xyz, rgb, scene, [int(c) for c in args.counts.split(",")], RasterOptions(tile_size=args.tile))
        if not args.render_only:
            for appearance in {"on": [True], "off": [False], "both": [False, True]}[args.appearance]:
                bench_optimize(scene, images, xyz, rgb, train, test, args, appearance)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"load average {load:.2f} at the end")
    return 0


if __name__ == "__main__":
    sys.exit(main())
