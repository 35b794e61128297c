"""SSIM of images with a separable Gaussian window, its blur a compiled kernel (numba).

The blur is the costly part of SSIM on the CPU: five local moments per channel, each an 11-tap
Gaussian in x and in y. With zero padding and a symmetric kernel the blur is its own adjoint, so the
backward pass is the same kernel applied to the incoming gradient. torch's grouped ``conv2d`` does the
same work several times slower on the CPU (fwd+bwd of the whole SSIM at 640x480: ~60-90 ms measured,
against ~10 ms for this), which made SSIM the dearest step of a splat iteration.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

import ffrecon.splat.raster  # noqa: F401  (selects numba's threading layer before any parallel call)


@njit(cache=True, parallel=True, fastmath=True)
def _blur(x, taps, out):
    """``out [C, H, W] = x`` convolved with ``taps [K]`` (odd K, symmetric) along W then H, zero padding.

    Works on zero-padded copies so that every index is a sum of non-negative loop variables: numba then
    drops its negative-index handling and the inner loops become SIMD code (4x faster measured)."""
    channels, height, width = x.shape
    k_len = len(taps)
    r = k_len // 2
    padded = np.zeros((channels, height, width + 2 * r), x.dtype)
    tmp = np.zeros((channels, height + 2 * r, width), x.dtype)
    for row in prange(channels * height):
        c, y = row // height, row % height
        for i in range(width):
            padded[c, y, r + i] = x[c, y, i]
        for k in range(k_len):
            w = taps[k]
            for i in range(width):
                tmp[c, r + y, i] += w * padded[c, y, i + k]
    for row in prange(channels * height):
        c, y = row // height, row % height
        for i in range(width):
            out[c, y, i] = 0.0
        for k in range(k_len):
            w = taps[k]
            for i in range(width):
                out[c, y, i] += w * tmp[c, y + k, i]


class _GaussianBlur(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, taps):
        ctx.taps = taps
        out = np.empty(x.shape, np.float32)
        _blur(x.detach().float().contiguous().numpy(), taps, out)
        return torch.from_numpy(out).to(x.dtype)

    @staticmethod
    def backward(ctx, grad):
        out = np.empty(grad.shape, np.float32)
        _blur(grad.detach().float().contiguous().numpy(), ctx.taps, out)  # self-adjoint: see the module docstring
        return torch.from_numpy(out).to(grad.dtype), None


def gaussian_taps(window: int = 11, sigma: float = 1.5) -> np.ndarray:
    """``[window]`` float32 normalised Gaussian taps."""
    coords = np.arange(window, dtype=np.float64) - window // 2
    g = np.exp(-(coords**2) / (2 * sigma**2))
    return (g / g.sum()).astype(np.float32)


def gaussian_blur(x: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """``[C, H, W]`` blurred by a separable Gaussian (zero padding, same size), differentiable; CPU only."""
    if x.device.type != "cpu":
        taps = torch.as_tensor(gaussian_taps(window, sigma), device=x.device, dtype=x.dtype)
        k = x.shape[0]
        pad = window // 2
        y = torch.nn.functional.conv2d(
            x[None], taps.view(1, 1, 1, -1).expand(k, 1, 1, window), padding=(0, pad), groups=k
        )
        return torch.nn.functional.conv2d(
            y, taps.view(1, 1, -1, 1).expand(k, 1, window, 1), padding=(pad, 0), groups=k
        )[0]
    return _GaussianBlur.apply(x, gaussian_taps(window, sigma))


@njit(cache=True, parallel=True, fastmath=True)
def _ssim_terms(x, y, moments, value, d_mx, d_exx, d_exy):
    """Per pixel SSIM ``value`` and its partial derivatives in the blurred moments of ``x`` (``my`` and
    ``eyy`` do not depend on ``x``), from ``moments [5C, H, W]`` = blurred (x, y, xx, yy, xy)."""
    channels, height, width = x.shape
    c1, c2 = 0.01**2, 0.03**2
    for row in prange(channels * height):
        c, r = row // height, row % height
        for i in range(width):
            mx, my = moments[c, r, i], moments[channels + c, r, i]
            exx, eyy, exy = (
                moments[2 * channels + c, r, i],
                moments[3 * channels + c, r, i],
                moments[4 * channels + c, r, i],
            )
            a = 2.0 * mx * my + c1
            b = 2.0 * (exy - mx * my) + c2
            cc = mx * mx + my * my + c1
            d = (exx - mx * mx) + (eyy - my * my) + c2
            s = a * b / (cc * d)
            value[c, r, i] = s
            d_mx[c, r, i] = s * (2.0 * my / a - 2.0 * my / b - 2.0 * mx / cc + 2.0 * mx / d)
            d_exx[c, r, i] = -s / d
            d_exy[c, r, i] = 2.0 * s / b


class _SSIMMean(torch.autograd.Function):
    """Mean SSIM of ``x`` against the constant ``y`` (``[C, H, W]`` float32), with the gradient in ``x``
    computed in the forward: ``(G*dS/dmx + 2x G*dS/dexx + y G*dS/dexy) / N`` (``G*``: the blur)."""

    @staticmethod
    def forward(ctx, x, y):
        xn, yn = x.detach().float().contiguous().numpy(), y.detach().float().contiguous().numpy()
        taps = gaussian_taps()
        stack = np.concatenate([xn, yn, xn * xn, yn * yn, xn * yn])
        moments = np.empty_like(stack)
        _blur(stack, taps, moments)
        terms = np.empty((4, *xn.shape), np.float32)
        _ssim_terms(xn, yn, moments, terms[0], terms[1], terms[2], terms[3])
        blurred = np.empty_like(terms[1:].reshape(-1, *xn.shape[1:]))
        _blur(np.ascontiguousarray(terms[1:].reshape(-1, *xn.shape[1:])), taps, blurred)
        g_mx, g_exx, g_exy = np.split(blurred, 3)
        ctx.grad = torch.from_numpy((g_mx + 2.0 * xn * g_exx + yn * g_exy) / xn.size)
        return torch.tensor(float(terms[0].mean(dtype=np.float64)), dtype=x.dtype)

    @staticmethod
    def backward(ctx, grad):
        return grad * ctx.grad, None


def ssim_mean(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Mean of :func:`ssim_map` (11-tap window, sigma 1.5) of ``[C, H, W]`` images, differentiable in ``x``
    (``y`` is treated as constant: the target photo). One fused compiled pass on the CPU."""
    if x.device.type != "cpu":
        return ssim_map(x, y).mean()
    return _SSIMMean.apply(x, y)


def ssim_map(x: torch.Tensor, y: torch.Tensor, *, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """SSIM map of ``[C, H, W]`` images in [0, 1] (Gaussian window, zero padding, standard C1, C2).

    All five local moments are blurred in one call (see the module docstring).
    """
    c = x.shape[0]
    stack = torch.cat([x, y, x * x, y * y, x * y])  # [5C, H, W]
    mx, my, exx, eyy, exy = gaussian_blur(stack, window, sigma).split(c)
    c1, c2 = 0.01**2, 0.03**2
    sxx, syy, sxy = exx - mx * mx, eyy - my * my, exy - mx * my
    return ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
