"""Microbenchmark behind the choice of kernel library for the CPU rasteriser: numba or warp-lang.

The same kernel in both: forward alpha compositing of 60k random 2D Gaussians at 640x480 over
per-tile, depth-sorted lists (16x16 tiles, about 330k pairs), one pixel per loop iteration, scalar
``exp``. numba runs its ``prange`` over tiles on every core; warp runs the kernel over pixels on its
"cpu" device. Both are installed from wheels, with no compiler at install time (numba ships LLVM
through llvmlite, warp its own clang/LLVM).

Usage (warp-lang is not a dependency of ffrecon; install it to compare):

    .venv/bin/pip install warp-lang
    .venv/bin/python tools/bench_kernel_libs.py
"""

from __future__ import annotations

import math
import os
import time

import numba
import numpy as np
from numba import njit, prange

W, H, N, TILE = 640, 480, 60_000, 16


def scene(seed: int = 0):
    """Random screen-space Gaussians and their per-tile, depth-sorted pair lists."""
    rng = np.random.default_rng(seed)
    means = (rng.random((N, 2)) * [W, H]).astype(np.float32)
    sigma = (np.exp(rng.normal(size=N) * 0.5) * 3.0).astype(np.float32)
    conic = np.stack([1 / sigma**2, np.zeros(N), 1 / sigma**2], 1).astype(np.float32)
    opacity = (rng.random(N) * 0.9 + 0.05).astype(np.float32)
    rgb = rng.random((N, 3)).astype(np.float32)
    radius = sigma * np.sqrt(2 * np.log(255 * opacity))
    tiles_x, tiles_y = math.ceil(W / TILE), math.ceil(H / TILE)
    lo = np.clip(((means - radius[:, None]) // TILE).astype(int), 0, [tiles_x - 1, tiles_y - 1])
    hi = np.clip(((means + radius[:, None]) // TILE).astype(int), 0, [tiles_x - 1, tiles_y - 1])
    gauss, tile = [], []
    for i in np.argsort(rng.random(N)):  # a random depth order
        for ty in range(lo[i, 1], hi[i, 1] + 1):
            for tx in range(lo[i, 0], hi[i, 0] + 1):
                gauss.append(i)
                tile.append(ty * tiles_x + tx)
    order = np.argsort(tile, kind="stable")
    gauss, tile = np.asarray(gauss, np.int32)[order], np.asarray(tile)[order]
    starts = np.searchsorted(tile, np.arange(tiles_x * tiles_y + 1)).astype(np.int64)
    return starts, gauss, means, conic, opacity, rgb, tiles_x


@njit(parallel=True)
def composite_numba(starts, gauss, means, conic, opacity, rgb, tiles_x, out):
    for t in prange(len(starts) - 1):
        x0, y0 = (t % tiles_x) * TILE, (t // tiles_x) * TILE
        for py in range(y0, min(y0 + TILE, H)):
            for px in range(x0, min(x0 + TILE, W)):
                trans, r, g, b = 1.0, 0.0, 0.0, 0.0
                for k in range(starts[t], starts[t + 1]):
                    i = gauss[k]
                    dx, dy = px + 0.5 - means[i, 0], py + 0.5 - means[i, 1]
                    s = 0.5 * (conic[i, 0] * dx * dx + conic[i, 2] * dy * dy) + conic[i, 1] * dx * dy
                    a = opacity[i] * math.exp(-s)
                    if a < 1.0 / 255.0:
                        continue
                    a = min(a, 0.999)
                    r += trans * a * rgb[i, 0]
                    g += trans * a * rgb[i, 1]
                    b += trans * a * rgb[i, 2]
                    trans *= 1.0 - a
                out[py, px, 0], out[py, px, 1], out[py, px, 2] = r, g, b


def median_ms(fn, repeats: int = 5) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def bench_warp(data, reference: np.ndarray) -> None:
    try:
        import warp as wp
    except ImportError:
        print("warp-lang: not installed (pip install warp-lang to compare)")
        return
    wp.config.quiet = True
    wp.init()
    starts, gauss, means, conic, opacity, rgb, tiles_x = data

    @wp.kernel
    def composite_warp(
        starts: wp.array(dtype=wp.int64),
        gauss: wp.array(dtype=wp.int32),
        means: wp.array(dtype=wp.vec2),
        conic: wp.array(dtype=wp.vec3),
        opacity: wp.array(dtype=wp.float32),
        rgb: wp.array(dtype=wp.vec3),
        tiles_x: int,
        out: wp.array(dtype=wp.vec3),
    ):
        pix = wp.tid()
        px, py = pix % W, pix // W
        t = (py // TILE) * tiles_x + px // TILE
        trans = float(1.0)
        acc = wp.vec3(0.0, 0.0, 0.0)
        for k in range(int(starts[t]), int(starts[t + 1])):
            i = gauss[k]
            d = wp.vec2(float(px) + 0.5, float(py) + 0.5) - means[i]
            c = conic[i]
            s = 0.5 * (c[0] * d[0] * d[0] + c[2] * d[1] * d[1]) + c[1] * d[0] * d[1]
            a = opacity[i] * wp.exp(-s)
            if a >= 1.0 / 255.0:
                a = wp.min(a, 0.999)
                acc = acc + trans * a * rgb[i]
                trans = trans * (1.0 - a)
        out[pix] = acc

    arrays = [
        wp.array(starts, dtype=wp.int64, device="cpu"),
        wp.array(gauss, dtype=wp.int32, device="cpu"),
        wp.array(means, dtype=wp.vec2, device="cpu"),
        wp.array(conic, dtype=wp.vec3, device="cpu"),
        wp.array(opacity, dtype=wp.float32, device="cpu"),
        wp.array(rgb, dtype=wp.vec3, device="cpu"),
        tiles_x,
    ]
    out = wp.zeros(W * H, dtype=wp.vec3, device="cpu")

    def run():
        wp.launch(composite_warp, dim=W * H, inputs=[*arrays, out], device="cpu")
        wp.synchronize()

    t0 = time.perf_counter()
    run()
    print(f"warp-lang {wp.config.version}: first launch (compiles) {time.perf_counter() - t0:.1f} s")
    print(f"warp-lang cpu device: {median_ms(run):.0f} ms")
    diff = np.abs(out.numpy().reshape(H, W, 3) - reference).max()
    print(f"largest difference from numba: {diff:.1e}")


def main() -> None:
    print(f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}")
    data = scene()
    print(f"{N} Gaussians, {W}x{H}, {len(data[1])} (tile, Gaussian) pairs")
    out = np.zeros((H, W, 3), np.float32)
    run = lambda: composite_numba(*data, out)  # noqa: E731
    t0 = time.perf_counter()
    run()
    print(f"numba {numba.__version__}: first call (compiles) {time.perf_counter() - t0:.1f} s")
    for threads in sorted({1, numba.config.NUMBA_NUM_THREADS}):
        numba.set_num_threads(threads)
        print(f"numba, {threads} thread(s): {median_ms(run):.0f} ms")
    bench_warp(data, out.copy())


if __name__ == "__main__":
    main()
