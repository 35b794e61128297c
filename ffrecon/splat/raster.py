"""Tile binning and depth-sorted alpha compositing of projected 2D Gaussians: compiled CPU kernels (numba).

The compositing rule (the one the brute-force reference in the tests implements too): for pixel
centre ``p`` and Gaussian ``k`` (sorted front to back by the camera-frame z of its centre),

    sigma_k(p) = 0.5 * (p - m_k)^T conic_k (p - m_k)
    alpha_k(p) = min(0.999, o_k * exp(-sigma_k(p)))   if o_k * exp(-sigma_k(p)) > 1/255, else 0
    out(p)     = sum_k T_k(p) alpha_k(p) f_k + T_N(p) background,   T_k = prod_{j<k} (1 - alpha_j)

with no early termination. Pixel centres follow COLMAP (see :mod:`ffrecon.geometry.projection`).

How the kernels are built, and why by hand: a (tile, Gaussian) pair exists only where the ellipse
``alpha > 1/255`` meets the tile's pixel centres (exact test). Per tile, pairs are visited front to
back and each is evaluated over the tile's pixels in one branch-free loop, which LLVM turns into SIMD
code; ``exp`` is a polynomial (:func:`_exp_nonpositive`, relative error ~1e-7) because numba only
vectorises ``math.exp`` with Intel's SVML, which is not a dependency here. Tiles run in parallel
(``prange``). The backward pass needs no stored per-pair state: it walks the pairs front to back
again and gets the suffix sums ``S_k`` of the gradient from the forward's output, ``S_k = out . g -
T_N g_alpha - sum_{j<=k} w_j g_j`` (no division by ``1 - alpha``, so no early termination is needed
to keep it stable). Gradients are written per pair (each pair belongs to one tile: no races) and summed
per Gaussian with ``index_add``.
"""

from __future__ import annotations

import contextlib
import math
import os
from dataclasses import dataclass

import numba
import numpy as np
import torch
from numba import njit, prange

if "NUMBA_THREADING_LAYER" not in os.environ:
    # numba's OpenMP layer busy-waits between parallel loops and fights torch's own OpenMP pool for the
    # cores (torch ops between two kernels measured 10-50x slower on 2 cores); its plain-thread
    # workqueue layer does not. Must be set before the first parallel call.
    numba.config.THREADING_LAYER = "workqueue"

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.999
_LOG_ALPHA_MIN = math.log(ALPHA_MIN)
PAIR_GRADS = 6  # per pair: d/d means2d (x, y), d/d conic (a, b, c), d/d log opacity


@dataclass(frozen=True)
class TileLayout:
    """Which Gaussians touch which tiles, front to back: tile ``t`` (row-major) owns the pairs
    ``tile_start[t] : tile_start[t + 1]`` and pair ``i`` is Gaussian ``pair_gauss[i]``."""

    tile_size: int
    tiles_x: int
    tiles_y: int
    tile_start: np.ndarray  # [tiles + 1] int64
    pair_gauss: np.ndarray  # [L] int64

    @property
    def num_tiles(self) -> int:
        return self.tiles_x * self.tiles_y

    @property
    def num_pairs(self) -> int:
        return len(self.pair_gauss)


@njit(cache=True)
def _constants(arr):
    """Constants in ``arr``'s float type, so float32 kernels stay float32 (a Python float literal
    would promote every expression it touches to float64 and halve the SIMD width)."""
    t = arr.dtype.type
    taylor = (t(1.0 / 40320.0), t(1.0 / 5040.0), t(1.0 / 720.0), t(1.0 / 120.0), t(1.0 / 24.0), t(1.0 / 6.0), t(0.5))
    return t(0.0), t(1.0), t(ALPHA_MIN), t(ALPHA_MAX), t(-6.0), t(0.0625), taylor


@njit(cache=True, fastmath=True)
def _exp_nonpositive(y, k):
    """``exp(y)`` for ``y`` in ``[-6, 0]`` (clamped below; callers discard results under 1/255 = e^-5.54).

    ``exp(y) = exp(y / 16)^16``: a degree-8 Taylor polynomial on ``[-0.375, 0]`` (truncation 4e-10)
    then four squarings, so relative error ~1e-7 in float32 (rounding, amplified 16x) and ~1e-8 in
    float64. Branch-free, so loops calling it vectorise.
    """
    zero, one, _, _, lowest, sixteenth, c = k
    z = max(y, lowest) * sixteenth
    p = c[0]
    for j in range(1, 7):
        p = p * z + c[j]
    p = (p * z + one) * z + one
    p = p * p
    p = p * p
    p = p * p
    return p * p


@njit(cache=True)
def _min_form_over_box(u, v, a, b, c, x0, x1, y0, y1):
    """Minimum over the box ``[x0, x1] x [y0, y1]`` of ``a dx^2 + 2 b dx dy + c dy^2``, ``(dx, dy)`` the
    offset from ``(u, v)``. Positive definite, so outside the box the minimum is on an edge, where the
    form is a 1D quadratic minimised in closed form and clamped."""
    if x0 <= u <= x1 and y0 <= v <= y1:
        return 0.0
    best = np.inf
    for dx in (x0 - u, x1 - u):
        dy = min(max(-b * dx / c, y0 - v), y1 - v)
        best = min(best, a * dx * dx + 2.0 * b * dx * dy + c * dy * dy)
    for dy in (y0 - v, y1 - v):
        dx = min(max(-b * dy / a, x0 - u), x1 - u)
        best = min(best, a * dx * dx + 2.0 * b * dx * dy + c * dy * dy)
    return best


@njit(cache=True)
def _tile_range(means2d, extent, i, width, height, tile_size, tiles_x, tiles_y):
    """Tiles ``[tx0, tx1) x [ty0, ty1)`` whose pixel centres the box ``means2d[i] +- extent[i]`` reaches."""
    lo_x = math.ceil(means2d[i, 0] - extent[i, 0] - 0.5)  # first column whose centre u + 0.5 is inside
    hi_x = math.floor(means2d[i, 0] + extent[i, 0] - 0.5)
    lo_y = math.ceil(means2d[i, 1] - extent[i, 1] - 0.5)
    hi_y = math.floor(means2d[i, 1] + extent[i, 1] - 0.5)
    if hi_x < 0 or hi_y < 0 or lo_x > width - 1 or lo_y > height - 1 or hi_x < lo_x or hi_y < lo_y:
        return 0, 0, 0, 0
    tx0, tx1 = max(lo_x, 0) // tile_size, min(hi_x, width - 1) // tile_size + 1
    ty0, ty1 = max(lo_y, 0) // tile_size, min(hi_y, height - 1) // tile_size + 1
    return tx0, tx1, ty0, ty1


@njit(cache=True)
def _meets(i, tx, ty, means2d, conics, log_opacity, width, height, tile_size):
    """Whether Gaussian ``i``'s ellipse ``alpha >= 1/255`` meets tile ``(tx, ty)``'s pixel centres (exact,
    up to a relative tolerance of 1e-4 that keeps borderline pairs)."""
    level = 2.0 * (log_opacity[i] - _LOG_ALPHA_MIN) * (1.0 + 1e-4) + 2e-4  # alpha >= 1/255 <=> form <= level
    y0, y1 = ty * tile_size + 0.5, min((ty + 1) * tile_size, height) - 0.5
    x0, x1 = tx * tile_size + 0.5, min((tx + 1) * tile_size, width) - 0.5
    form = _min_form_over_box(means2d[i, 0], means2d[i, 1], conics[i, 0], conics[i, 1], conics[i, 2], x0, x1, y0, y1)
    return form <= level


@njit(cache=True, parallel=True)
def _candidates(order, means2d, conics, log_opacity, extent, width, height, tile_size, tiles_x, tiles_y):
    """Per Gaussian of ``order``, the tiles its box reaches, ``-1`` where the exact test rejects them:
    ``(offsets [n + 1], tiles [offsets[-1]])``, Gaussian ``order[j]`` owning ``offsets[j]:offsets[j + 1]``."""
    n = len(order)
    boxes = np.empty((n, 4), np.int64)
    offsets = np.zeros(n + 1, np.int64)
    for j in prange(n):
        tx0, tx1, ty0, ty1 = _tile_range(means2d, extent, order[j], width, height, tile_size, tiles_x, tiles_y)
        boxes[j, 0], boxes[j, 1], boxes[j, 2], boxes[j, 3] = tx0, tx1, ty0, ty1
        offsets[j + 1] = (tx1 - tx0) * (ty1 - ty0)
    offsets = np.cumsum(offsets)
    tiles = np.empty(offsets[-1], np.int64)
    for j in prange(n):
        m = offsets[j]
        for ty in range(boxes[j, 2], boxes[j, 3]):
            for tx in range(boxes[j, 0], boxes[j, 1]):
                hit = _meets(order[j], tx, ty, means2d, conics, log_opacity, width, height, tile_size)
                tiles[m] = ty * tiles_x + tx if hit else -1
                m += 1
    return offsets, tiles


@njit(cache=True)
def _group_by_tile(order, offsets, tiles, num_tiles):
    """Counting sort of the accepted candidates by tile; stable, so each tile's pairs stay front to back."""
    counts = np.zeros(num_tiles + 1, np.int64)
    for t in tiles:
        if t >= 0:
            counts[t + 1] += 1
    tile_start = np.cumsum(counts)
    fill = tile_start[:-1].copy()
    pair_gauss = np.empty(tile_start[-1], np.int64)
    for j in range(len(order)):
        for m in range(offsets[j], offsets[j + 1]):
            t = tiles[m]
            if t >= 0:
                pair_gauss[fill[t]] = order[j]
                fill[t] += 1
    return tile_start, pair_gauss


def bin_gaussians(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    log_opacity: torch.Tensor,
    extent: torch.Tensor,
    depth: torch.Tensor,
    visible: torch.Tensor,
    width: int,
    height: int,
    *,
    tile_size: int = 16,
) -> TileLayout:
    """Assign the visible Gaussians to the tiles whose pixel centres their ellipse ``alpha >= 1/255``
    reaches, front to back (stable sort on ``depth``) within each tile.

    Args:
        means2d: ``[N, 2]`` pixel positions (COLMAP convention); conics: ``[N, 3]`` (a, b, c) of the
            inverse 2D covariance; log_opacity: ``[N]``; extent: ``[N, 2]`` half-widths in pixels of
            the box outside which alpha < 1/255; depth: ``[N]`` sort key; visible: ``[N]`` bool.
    """
    with torch.no_grad():
        ids = torch.nonzero(visible).squeeze(1)
        order = ids[torch.argsort(depth.detach()[ids], stable=True)].numpy()
        arrays = [t.detach().double().numpy() for t in (means2d, conics, log_opacity, extent)]
    tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
    offsets, candidates = _candidates(order, *arrays, width, height, tile_size, tiles_x, tiles_y)
    tile_start, pair_gauss = _group_by_tile(order, offsets, candidates, tiles_x * tiles_y)
    return TileLayout(tile_size, tiles_x, tiles_y, tile_start, pair_gauss)


@njit(cache=True, fastmath=True)
def _pair_coefficients(means2d, conics, log_opacity, g, cx, cy):
    """Coefficients of ``log(o) - sigma`` as ``-(c0 x^2 + c1 xy + c2 y^2 + c3 x + c4 y + c5)`` in pixel
    coordinates ``(x, y)`` relative to the tile centre ``(cx, cy)`` (small numbers: no cancellation)."""
    t = conics.dtype.type
    u, v = means2d[g, 0] - cx, means2d[g, 1] - cy
    a, b, c = conics[g, 0], conics[g, 1], conics[g, 2]
    const = 0.5 * a * u * u + b * u * v + 0.5 * c * v * v - log_opacity[g]
    return t(0.5 * a), b, t(0.5 * c), t(-(a * u + b * v)), t(-(b * u + c * v)), t(const), u, v


@njit(cache=True, fastmath=True)
def _tile_pixels(t, tiles_x, tile_size, width, height, dtype):
    """Pixel coordinates ``(x, y)`` relative to tile ``t``'s centre, the tile centre, and the tile's
    first column/row and size clipped to the image."""
    x0, y0 = (t % tiles_x) * tile_size, (t // tiles_x) * tile_size
    nx, ny = min(tile_size, width - x0), min(tile_size, height - y0)
    half = 0.5 * tile_size
    lx = np.empty(nx * ny, dtype)
    ly = np.empty(nx * ny, dtype)
    for j in range(ny):
        for i in range(nx):
            lx[j * nx + i] = i + 0.5 - half
            ly[j * nx + i] = j + 0.5 - half
    return lx, ly, x0 + half, y0 + half, x0, y0, nx, ny


@njit(cache=True, fastmath=True)
def _alphas(c0, c1, c2, c3, c4, c5, lx, ly, alpha, k):
    """Writes the clamped alpha of one pair at the tile's pixels into ``alpha`` (0 below 1/255)."""
    zero, _, a_min, a_max, _, _, _ = k
    for p in range(len(lx)):
        x, y = lx[p], ly[p]
        a = _exp_nonpositive(-(c0 * x * x + c1 * x * y + c2 * y * y + c3 * x + c4 * y + c5), k)
        alpha[p] = min(a, a_max) if a > a_min else zero


@njit(cache=True, parallel=True, fastmath=True)
def _forward(
    tile_start, pair_gauss, means2d, conics, log_opacity, feat, background, tile_size, tiles_x, tile_order, out, t_final
):
    """Composite every tile (in ``tile_order``) into ``out [H, W, F]`` and ``t_final [H, W]`` (final
    transmittance)."""
    height, width, num_feat = out.shape
    dtype = out.dtype
    for i in prange(len(tile_order)):
        t = tile_order[i]
        k_const = _constants(out)  # inside the loop: numba's parallel wrapper cannot take a tuple in
        one = k_const[1]
        lx, ly, cx, cy, x0, y0, nx, ny = _tile_pixels(t, tiles_x, tile_size, width, height, dtype)
        n = nx * ny
        trans = np.ones(n, dtype)
        acc = np.zeros((num_feat, n), dtype)
        alpha = np.empty(n, dtype)
        for k in range(tile_start[t], tile_start[t + 1]):
            g = pair_gauss[k]
            c0, c1, c2, c3, c4, c5, _, _ = _pair_coefficients(means2d, conics, log_opacity, g, cx, cy)
            _alphas(c0, c1, c2, c3, c4, c5, lx, ly, alpha, k_const)
            for f in range(num_feat):
                fg = feat[g, f]
                for p in range(n):
                    acc[f, p] += trans[p] * alpha[p] * fg
            for p in range(n):
                trans[p] *= one - alpha[p]
        for p in range(n):
            row, col = y0 + p // nx, x0 + p % nx
            for f in range(num_feat):
                out[row, col, f] = acc[f, p] + trans[p] * background[f]
            t_final[row, col] = trans[p]


@njit(inline="always")
def _tile_seed(out, t_final, grad_out, grad_alpha, x0, y0, nx, n, grad_bg_mine):
    """The tile's incoming gradient ``g_out [F, n]`` and ``rest [n]``, the suffix sum before any pair
    (``S = out . g - T_N g_alpha``); adds the background's gradient into ``grad_bg_mine [F]``."""
    num_feat, dtype = out.shape[2], out.dtype
    g_out = np.empty((num_feat, n), dtype)
    rest = np.empty(n, dtype)
    for p in range(n):
        row, col = y0 + p // nx, x0 + p % nx
        rest[p] = -t_final[row, col] * grad_alpha[row, col]
        for f in range(num_feat):
            g_out[f, p] = grad_out[row, col, f]
            rest[p] += out[row, col, f] * g_out[f, p]
            grad_bg_mine[f] += t_final[row, col] * g_out[f, p]
    return g_out, rest


@njit(inline="always")
def _add_pair_grads(grad_gauss_mine, g, conics, u, v, g0, g1, g2, g3, g4, g5):
    """The chain rule from a pair's coefficients ``(c0..c5)`` of :func:`_pair_coefficients` (their gradients
    ``g0..g5``) to Gaussian ``g``'s ``(u, v, a, b, c, log o)``, added into ``grad_gauss_mine [N, 6 + F]``;
    ``u, v`` are relative to the tile centre."""
    a, b, c = conics[g, 0], conics[g, 1], conics[g, 2]
    grad_gauss_mine[g, 0] += -a * g3 - b * g4 + (a * u + b * v) * g5
    grad_gauss_mine[g, 1] += -b * g3 - c * g4 + (b * u + c * v) * g5
    grad_gauss_mine[g, 2] += 0.5 * g0 - u * g3 + 0.5 * u * u * g5
    grad_gauss_mine[g, 3] += g1 - v * g3 - u * g4 + u * v * g5
    grad_gauss_mine[g, 4] += 0.5 * g2 - v * g4 + 0.5 * v * v * g5
    grad_gauss_mine[g, 5] += -g5


@njit(cache=True, parallel=True, fastmath=True)
def _backward(
    tile_start,
    pair_gauss,
    means2d,
    conics,
    log_opacity,
    feat,
    background,
    tile_size,
    tiles_x,
    out,
    t_final,
    grad_out,
    grad_alpha,
    tile_order,
    grad_gauss,
    grad_bg,
):
    """Gradients (see the module docstring) added into ``grad_gauss [threads, N, 6 + F]`` (means2d x, y;
    conic a, b, c; log opacity; features) and ``grad_bg [threads, F]``, one slice per thread (no races;
    the caller sums them). Tiles are visited in ``tile_order``; per tile the incoming gradient
    (:func:`_tile_seed`), then per pair, front to back, its features, its alphas and the chain rule to its 2D
    Gaussian (:func:`_add_pair_grads`). The helpers are inlined in numba's IR (``inline="always"``): as compiled
    calls, a per-pair one with a loop measured 2.8x slower and changed the float32 gradients' last bits.
    """
    height, width, num_feat = out.shape
    dtype = out.dtype
    for i in prange(len(tile_order)):
        t = tile_order[i]
        mine = numba.get_thread_id()
        k_const = _constants(out)
        zero, one, a_max = k_const[0], k_const[1], k_const[3]
        lx, ly, cx, cy, x0, y0, nx, ny = _tile_pixels(t, tiles_x, tile_size, width, height, dtype)
        n = nx * ny
        g_out, rest = _tile_seed(out, t_final, grad_out, grad_alpha, x0, y0, nx, n, grad_bg[mine])
        trans = np.ones(n, dtype)
        alpha = np.empty(n, dtype)
        wg = np.empty(n, dtype)
        for k in range(tile_start[t], tile_start[t + 1]):
            g = pair_gauss[k]
            c0, c1, c2, c3, c4, c5, u, v = _pair_coefficients(means2d, conics, log_opacity, g, cx, cy)
            _alphas(c0, c1, c2, c3, c4, c5, lx, ly, alpha, k_const)
            for p in range(n):
                wg[p] = zero
            for f in range(num_feat):
                fg = feat[g, f]
                s = zero
                for p in range(n):
                    w = trans[p] * alpha[p]
                    wg[p] += w * fg * g_out[f, p]
                    s += w * g_out[f, p]
                grad_gauss[mine, g, PAIR_GRADS + f] += s
            # dL/dy for y = log(alpha) before the clamp: (w g - alpha / (1 - alpha) S) where unclamped.
            g0 = g1 = g2 = g3 = g4 = g5 = zero
            for p in range(n):
                a = alpha[p]
                rest[p] -= wg[p]  # now S_k
                dy = (wg[p] - a / (one - a) * rest[p]) if a < a_max else zero
                trans[p] *= one - a
                x, y = lx[p], ly[p]
                g0 -= dy * x * x  # y = -(c . basis): dL/dc_j = -sum_p dL/dy_p basis_j(p)
                g1 -= dy * x * y
                g2 -= dy * y * y
                g3 -= dy * x
                g4 -= dy * y
                g5 -= dy
            _add_pair_grads(grad_gauss[mine], g, conics, u, v, g0, g1, g2, g3, g4, g5)


def _numpy(x: torch.Tensor, dtype: torch.dtype) -> np.ndarray:
    return x.detach().to(dtype).contiguous().numpy()


class _Composite(torch.autograd.Function):
    """``(means2d [N, 2], conics [N, 3], log_opacity [N], feat [N, F], background [F]) ->
    (features [H, W, F], alpha [H, W])`` through the compiled kernels."""

    @staticmethod
    def forward(ctx, means2d, conics, log_opacity, feat, background, layout: TileLayout, width: int, height: int):
        dtype = feat.dtype
        inputs = [_numpy(x, dtype) for x in (means2d, conics, log_opacity, feat, background)]
        out = np.empty((height, width, feat.shape[1]), inputs[0].dtype)
        t_final = np.empty((height, width), inputs[0].dtype)
        order = _balanced_tile_order(layout)
        _forward(layout.tile_start, layout.pair_gauss, *inputs, layout.tile_size, layout.tiles_x, order, out, t_final)
        if any(ctx.needs_input_grad[:5]):
            _compile_backward(out.dtype, feat.shape[1])
        ctx.layout, ctx.inputs, ctx.out, ctx.t_final = layout, inputs, out, t_final
        return torch.from_numpy(out), torch.from_numpy(1.0 - t_final)

    @staticmethod
    def backward(ctx, grad_out, grad_alpha):
        layout: TileLayout = ctx.layout
        torch_dtype = torch.from_numpy(ctx.out[:0]).dtype
        num, num_feat = ctx.inputs[3].shape
        threads = numba.get_num_threads()
        grad_gauss = np.zeros((threads, num, PAIR_GRADS + num_feat), ctx.out.dtype)
        grad_bg = np.zeros((threads, num_feat), ctx.out.dtype)
        _backward(
            layout.tile_start,
            layout.pair_gauss,
            *ctx.inputs,
            layout.tile_size,
            layout.tiles_x,
            ctx.out,
            ctx.t_final,
            _numpy(grad_out, torch_dtype),
            _numpy(grad_alpha, torch_dtype),
            _balanced_tile_order(layout),
            grad_gauss,
            grad_bg,
        )
        ctx.inputs = ctx.out = ctx.t_final = None
        per_gauss = torch.from_numpy(grad_gauss.sum(axis=0) if threads > 1 else grad_gauss[0])
        grads = (per_gauss[:, :2], per_gauss[:, 2:5], per_gauss[:, 5], per_gauss[:, PAIR_GRADS:])
        return (*grads, torch.from_numpy(grad_bg.sum(axis=0)), None, None, None)


_BACKWARD_READY: set[np.dtype] = set()


def _compile_backward(dtype: np.dtype, num_feat: int) -> None:
    """Compile (or load from numba's cache) the backward kernel for ``dtype`` now, on an empty image.

    Here in the forward, not lazily in the backward: torch runs the backward inside its autograd engine,
    where a Ctrl-C that lands during LLVM code generation is swallowed by llvmlite's callback and the
    process hangs (reproduced). A Ctrl-C here is an ordinary KeyboardInterrupt.
    """
    if dtype in _BACKWARD_READY:
        return
    z, threads = np.zeros, numba.get_num_threads()
    gaussians = (z((1, 2), dtype), z((1, 3), dtype), z(1, dtype), z((1, num_feat), dtype), z(num_feat, dtype))
    image = (z((1, 1, num_feat), dtype), np.ones((1, 1), dtype), z((1, 1, num_feat), dtype), z((1, 1), dtype))
    grads = (z((threads, 1, PAIR_GRADS + num_feat), dtype), z((threads, num_feat), dtype))
    _backward(z(2, np.int64), z(0, np.int64), *gaussians, 1, 1, *image, np.argsort(z(1, np.int64)), *grads)
    _BACKWARD_READY.add(dtype)


def _balanced_tile_order(layout: TileLayout) -> np.ndarray:
    """Tiles ordered so that numba's static split of a ``prange`` gives each thread every
    ``threads``-th row of tiles (the busy rows of an image are next to each other). Fixed for a given
    thread count, so results are deterministic."""
    threads = numba.get_num_threads()
    rows = np.arange(layout.num_tiles) // layout.tiles_x
    return np.argsort(rows % threads, kind="stable")


def composite(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    log_opacity: torch.Tensor,
    feat: torch.Tensor,
    background: torch.Tensor,
    layout: TileLayout,
    width: int,
    height: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite the Gaussians' features into an image, differentiably.

    Args:
        means2d: ``[N, 2]``, conics: ``[N, 3]``, log_opacity: ``[N]`` as from
            :func:`ffrecon.splat.project.project_gaussians`; feat: ``[N, F]`` per-Gaussian features (rgb,
            depth); background: ``[F]``. All of one float dtype (float32 or float64).
        layout: from :func:`bin_gaussians` with the same means, conics and opacities.
    Returns:
        ``features [height, width, F]`` and ``alpha [height, width]`` (1 - final transmittance).
    """
    return _Composite.apply(means2d, conics, log_opacity, feat, background, layout, width, height)


def kernel_threads() -> int:
    """Cores this process may use (the compiled kernels' default thread count)."""
    available = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(available, numba.config.NUMBA_NUM_THREADS))


@contextlib.contextmanager
def raster_threads(num: int):
    """Run the compiled kernels on ``num`` threads inside the block (clipped to numba's pool)."""
    before = numba.get_num_threads()
    numba.set_num_threads(max(1, min(num, numba.config.NUMBA_NUM_THREADS)))
    try:
        yield
    finally:
        numba.set_num_threads(before)
