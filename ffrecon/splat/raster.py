"""Tile binning and depth-sorted alpha compositing of projected 2D Gaussians, on the CPU.

The compositing rule (the one the brute-force reference in the tests implements too): for pixel
centre ``p`` and Gaussian ``k`` (sorted front to back by the camera-frame z of its centre),

    sigma_k(p) = 0.5 * (p - m_k)^T conic_k (p - m_k)
    alpha_k(p) = min(0.999, o_k * exp(-sigma_k(p)))   if o_k * exp(-sigma_k(p)) > 1/255, else 0
    out(p)     = sum_k T_k(p) alpha_k(p) f_k + T_N(p) background,   T_k = prod_{j<k} (1 - alpha_j)

with no early termination. Pixel centres follow COLMAP (see :mod:`ffrecon.geometry.projection`).

Speed comes from four choices. A (tile, Gaussian) pair exists only where the ellipse
``alpha > 1/255`` meets the tile (exact test). Each pair stores ``sigma - log(o)`` as a quadratic
in tile-local pixel coordinates, so all of a tile's alphas are one matrix product with a fixed
``[6, P]`` basis and an ``exp``. Tiles are sorted by how many Gaussians touch them and grouped into
chunks padded to the largest count in the chunk (little padding, bounded memory, no Python loop
over pixels or Gaussians). And the backward pass is written by hand: per chunk it needs only the
blending weights and ``alpha / (1 - alpha)``, which the forward keeps (or, past a memory cap,
recomputes as the CUDA rasterisers do), instead of autograd storing every intermediate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.999
PAD_LOG_TERM = 1.0e4  # constant term of padding pairs: exp(-1e4) == 0, so they never contribute


@dataclass(frozen=True)
class TileLayout:
    """Which Gaussians touch which tiles, sorted by depth, grouped into padded chunks.

    ``pair_gauss[i]`` is the Gaussian of padded pair ``i`` (``num_gaussians`` for padding) and
    ``pair_origin[i]`` the pixel position of the centre of its tile. Chunk ``c`` covers padded pairs
    ``starts[c] : starts[c] + len(tile_ids[c]) * ks[c]`` as a ``[b, K]`` block.
    """

    tile_size: int
    tiles_x: int
    tiles_y: int
    pair_gauss: torch.Tensor  # [L] int64
    pair_origin: torch.Tensor  # [L, 2] float32, (x, y) of the tile centre
    tile_ids: tuple[torch.Tensor, ...]  # per chunk, [b] int64 tile indices (row-major)
    starts: tuple[int, ...]
    ks: tuple[int, ...]
    num_pairs: int  # unpadded (tile, Gaussian) pairs

    @property
    def num_tiles(self) -> int:
        return self.tiles_x * self.tiles_y

    @property
    def padded_evaluations(self) -> int:
        """Number of (pixel, Gaussian) evaluations one forward pass makes, padding included."""
        return sum(len(t) * k for t, k in zip(self.tile_ids, self.ks)) * self.tile_size**2


def _take(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``x[index]`` along dim 0 (index_select: faster than fancy indexing on the CPU)."""
    return torch.index_select(x, 0, index)


def _min_quadratic_over_box(m: torch.Tensor, conic: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """Minimum over the boxes ``[lo, hi]`` (``[M, 2]``) of ``(p - m)^T [[a, b], [b, c]] (p - m)``.

    The form is positive definite, so when ``m`` is outside the box the minimum lies on one of its
    four edges, where it is a 1D quadratic minimised in closed form and clamped to the edge.
    """
    a, b, c = conic.unbind(1)
    d_lo, d_hi = lo - m, hi - m  # box corners relative to the centre
    best = torch.full_like(a, float("inf"))
    for dx in (d_lo[:, 0], d_hi[:, 0]):  # vertical edges
        dy = torch.clamp(-b * dx / c, d_lo[:, 1], d_hi[:, 1])
        best = torch.minimum(best, a * dx * dx + 2 * b * dx * dy + c * dy * dy)
    for dy in (d_lo[:, 1], d_hi[:, 1]):  # horizontal edges
        dx = torch.clamp(-b * dy / a, d_lo[:, 0], d_hi[:, 0])
        best = torch.minimum(best, a * dx * dx + 2 * b * dx * dy + c * dy * dy)
    inside = (d_lo <= 0).all(1) & (d_hi >= 0).all(1)
    return torch.where(inside, torch.zeros_like(best), best)


def bin_gaussians(
    means2d: torch.Tensor,
    extent: torch.Tensor,
    depth: torch.Tensor,
    visible: torch.Tensor,
    width: int,
    height: int,
    *,
    conics: torch.Tensor | None = None,
    log_opacity: torch.Tensor | None = None,
    tile_size: int = 16,
    chunk_elements: int = 1 << 18,
) -> TileLayout:
    """Assign visible Gaussians to the tiles their ``alpha >= 1/255`` region overlaps.

    Args:
        means2d: ``[N, 2]`` pixel positions (COLMAP convention), no gradient needed.
        extent: ``[N, 2]`` half-widths in pixels of the axis-aligned box outside which alpha < 1/255.
        depth: ``[N]`` sort key (camera-frame z of the centre).
        visible: ``[N]`` bool.
        conics, log_opacity: ``[N, 3]`` and ``[N]``; when given, a (tile, Gaussian) pair is dropped
            unless the ellipse ``alpha >= 1/255`` meets the tile's pixel centres (exact test, not
            just the bounding box: about a quarter fewer pairs for round Gaussians).
        chunk_elements: target size of one chunk's ``[b, K, P]`` work arrays (memory vs overhead).
    """
    tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
    with torch.no_grad():
        pair_g, tile = _box_pairs(means2d, extent, depth, visible, width, height, tile_size)
        if conics is not None and log_opacity is not None and len(tile):
            meets = _ellipse_meets_tile(means2d, conics, log_opacity, pair_g, tile, width, height, tiles_x, tile_size)
            pair_g, tile = _take(pair_g, meets), _take(tile, meets)
        order = torch.argsort(tile, stable=True)  # by tile, then depth (pairs were depth-ordered)
        pair_g, tile = _take(pair_g, order), _take(tile, order)
        return _padded_chunks(pair_g, tile, means2d.shape[0], tiles_x, tiles_y, tile_size, chunk_elements)


def _box_pairs(
    means2d: torch.Tensor,
    extent: torch.Tensor,
    depth: torch.Tensor,
    visible: torch.Tensor,
    width: int,
    height: int,
    tile_size: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(gaussian [L], tile [L])`` int64: one pair per tile that a visible Gaussian's box overlaps.

    Pairs come Gaussian by Gaussian, front to back (stable sort on ``depth``); tiles are row-major.
    """
    # Range of pixel columns whose centre (u + 0.5) lies within [x - e, x + e], clipped to the image.
    lo = torch.ceil(means2d - extent - 0.5)
    hi = torch.floor(means2d + extent - 0.5)
    lo_x, lo_y = lo[:, 0].clamp(0, width - 1), lo[:, 1].clamp(0, height - 1)
    hi_x, hi_y = hi[:, 0].clamp(0, width - 1), hi[:, 1].clamp(0, height - 1)
    hits = visible & (hi[:, 0] >= lo_x) & (lo[:, 0] <= hi_x) & (hi[:, 1] >= lo_y) & (lo[:, 1] <= hi_y)
    hits &= (hi[:, 0] >= 0) & (lo[:, 0] <= width - 1) & (hi[:, 1] >= 0) & (lo[:, 1] <= height - 1)
    gid = torch.nonzero(hits).squeeze(1)
    gid = _take(gid, torch.argsort(_take(depth, gid), stable=True))  # front to back
    tx0 = (_take(lo_x, gid) // tile_size).long()
    ty0 = (_take(lo_y, gid) // tile_size).long()
    nx = (_take(hi_x, gid) // tile_size).long() - tx0 + 1
    ny = (_take(hi_y, gid) // tile_size).long() - ty0 + 1
    counts = nx * ny
    total = int(counts.sum())
    pair_g = torch.repeat_interleave(gid, counts)
    first = torch.repeat_interleave(torch.cumsum(counts, 0) - counts, counts)
    local = torch.arange(total) - first
    nx_rep = torch.repeat_interleave(nx, counts)
    tiles_x = math.ceil(width / tile_size)
    tile = (
        (torch.repeat_interleave(ty0, counts) + local // nx_rep) * tiles_x
        + torch.repeat_interleave(tx0, counts)
        + local % nx_rep
    )
    return pair_g, tile


def _ellipse_meets_tile(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    log_opacity: torch.Tensor,
    pair_g: torch.Tensor,
    tile: torch.Tensor,
    width: int,
    height: int,
    tiles_x: int,
    tile_size: int,
) -> torch.Tensor:
    """Indices of the pairs whose ellipse ``alpha >= 1/255`` contains one of the tile's pixel centres
    (or nearly: a relative tolerance of 1e-4 keeps borderline pairs)."""
    corner = torch.stack([tile % tiles_x, tile // tiles_x], 1) * tile_size
    box_lo = corner + 0.5  # first and last pixel centres of the tile, clipped to the image
    box_hi = torch.minimum(corner + tile_size, torch.tensor([width, height])) - 0.5
    q = _min_quadratic_over_box(
        _take(means2d, pair_g), _take(conics, pair_g), box_lo.to(means2d.dtype), box_hi.to(means2d.dtype)
    )
    level = _take(log_opacity, pair_g) - math.log(ALPHA_MIN)  # alpha >= 1/255  <=>  q / 2 <= level
    meets = 0.5 * q <= level * (1 + 1e-4) + 1e-4
    return torch.nonzero(meets).squeeze(1)


def _padded_chunks(
    pair_g: torch.Tensor,
    tile: torch.Tensor,
    num_gaussians: int,
    tiles_x: int,
    tiles_y: int,
    tile_size: int,
    chunk_elements: int,
) -> TileLayout:
    """Group the tiles into chunks padded to a common pair count (see :class:`TileLayout`).

    ``pair_g`` and ``tile`` are sorted by tile, then front to back. Tiles are taken from the busiest
    down and cut greedily into chunks of about ``chunk_elements`` evaluations, each padded to its
    first (largest) count with the index ``num_gaussians``.
    """
    total = len(tile)
    per_tile = torch.bincount(tile, minlength=tiles_x * tiles_y)
    tile_start = torch.cumsum(per_tile, 0) - per_tile
    busy = torch.argsort(per_tile, descending=True, stable=True)
    busy_counts = per_tile[busy].tolist()
    num_busy = sum(1 for c in busy_counts if c > 0)
    busy = busy[:num_busy]
    p = tile_size * tile_size
    bounds, i = [], 0
    while i < num_busy:
        k = busy_counts[i]
        j = min(num_busy, i + max(1, chunk_elements // (k * p)))
        bounds.append((i, j, k))
        i = j
    sizes = [j - i for i, j, _ in bounds]
    ks = [k for _, _, k in bounds]
    starts = [sum(a * b for a, b in zip(sizes[:c], ks[:c])) for c in range(len(bounds))]
    padded = torch.repeat_interleave(
        torch.tensor(ks, dtype=torch.long), torch.tensor(sizes, dtype=torch.long)
    )  # per busy tile
    row = torch.repeat_interleave(torch.arange(num_busy), padded)
    slot = torch.arange(int(padded.sum())) - torch.repeat_interleave(torch.cumsum(padded, 0) - padded, padded)
    pad_index = torch.where(
        slot < _take(_take(per_tile, busy), row), _take(_take(tile_start, busy), row) + slot, total
    )  # `total` = padding
    pair_gauss = _take(torch.cat([pair_g, torch.tensor([num_gaussians])]), pad_index)
    tile_of_pair = _take(torch.cat([tile, torch.tensor([0])]), pad_index)
    origin = (
        torch.stack([(tile_of_pair % tiles_x).float(), (tile_of_pair // tiles_x).float()], 1) * tile_size
        + tile_size / 2
    )
    chunks_tiles = tuple(busy[i:j] for i, j, _ in bounds)
    return TileLayout(tile_size, tiles_x, tiles_y, pair_gauss, origin, chunks_tiles, tuple(starts), tuple(ks), total)


def tile_basis(tile_size: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """``[6, P]`` monomials ``(x^2, xy, y^2, x, y, 1)`` of the pixel centres relative to the tile centre."""
    c = torch.arange(tile_size, dtype=torch.float64) + 0.5 - tile_size / 2
    ly, lx = torch.meshgrid(c, c, indexing="ij")
    lx, ly = lx.reshape(-1), ly.reshape(-1)
    return torch.stack([lx * lx, lx * ly, ly * ly, lx, ly, torch.ones_like(lx)]).to(dtype)


def pair_coefficients(
    means2d: torch.Tensor, conics: torch.Tensor, log_opacity: torch.Tensor, layout: TileLayout
) -> torch.Tensor:
    """``[L, 6]`` coefficients of ``sigma - log(o)`` as a quadratic in tile-local pixel coordinates.

    Differentiable (autograd) in ``means2d [N, 2]``, ``conics [N, 3]`` (a, b, c of the inverse 2D
    covariance ``[[a, b], [b, c]]``) and ``log_opacity [N]``. Padding pairs get a huge constant term.
    """
    pad = PAD_LOG_TERM
    # index_select (backward: index_add) rather than fancy indexing (backward: a sorting index_put).
    idx = layout.pair_gauss
    m = torch.index_select(torch.cat([means2d, means2d.new_zeros(1, 2)]), 0, idx) - layout.pair_origin.to(means2d.dtype)
    con = torch.index_select(torch.cat([conics, conics.new_zeros(1, 3)]), 0, idx)
    log_o = torch.index_select(torch.cat([log_opacity, log_opacity.new_full((1,), -pad)]), 0, idx)
    a, b, c = con.unbind(1)
    u, v = m.unbind(1)
    const = 0.5 * a * u * u + b * u * v + 0.5 * c * v * v - log_o
    return torch.stack([0.5 * a, b, 0.5 * c, -(a * u + b * v), -(b * u + c * v), const], dim=1)


def _chunk_forward(
    coef: torch.Tensor, basis: torch.Tensor, feat: torch.Tensor, background: torch.Tensor
) -> tuple[torch.Tensor, tuple]:
    """Composite one chunk.

    Args:
        coef: ``[b, K, 6]``; basis: ``[6, P]``; feat: ``[b, K, F]``; background: ``[F]``.
    Returns:
        ``out [b, P, F]`` and what the backward needs: the weights ``w_k = T_k alpha_k``, the ratios
        ``alpha_k / (1 - alpha_k)``, the mask of unclamped alphas and the final transmittance.
    """
    alpha = torch.exp_(torch.matmul(-coef, basis))  # o * exp(-sigma), [b, K, P]
    torch.nn.functional.threshold_(alpha, ALPHA_MIN, 0.0)
    unclamped = alpha < ALPHA_MAX
    alpha.clamp_(max=ALPHA_MAX)
    one_minus = 1.0 - alpha
    b, k, p = alpha.shape
    trans = alpha.new_empty(b, k + 1, p)
    trans[:, 0] = 1.0
    torch.cumprod(one_minus, dim=1, out=trans[:, 1:])
    weight = trans[:, :-1] - trans[:, 1:]  # T_k - T_{k+1} = T_k alpha_k
    t_final = trans[:, -1]
    out = torch.baddbmm(t_final[:, :, None] * background, weight.transpose(1, 2), feat)
    ratio = alpha.div_(one_minus)
    return out, (weight, ratio, unclamped, t_final)


class _Composite(torch.autograd.Function):
    """``(coef [L, 6], feat [L, F], background [F]) -> (features [tiles, P, F], alpha [tiles, P])``,
    with a hand-written backward.

    For output ``o = sum_k w_k f_k + T_N bg`` with ``w_k = T_k alpha_k`` and ``s_k = -log alpha_k``
    (before clamping), ``dL/ds_k = -(w_k g_k - alpha_k / (1 - alpha_k) S_k)`` where
    ``g_k = f_k . dL/do`` and ``S_k = sum_{j>k} w_j g_j + T_N bg . dL/do``. The forward keeps each
    chunk's ``w``, ``alpha / (1 - alpha)`` and masks for the backward while they total at most
    ``cache_elements`` values; past that the backward recomputes them chunk by chunk.
    """

    @staticmethod
    def forward(ctx, coef, feat, background, layout: TileLayout, cache_elements: int):
        basis = tile_basis(layout.tile_size, coef.dtype)
        p = basis.shape[1]
        out = background.detach().expand(layout.num_tiles, p, feat.shape[1]).clone()
        out_alpha = coef.new_zeros(layout.num_tiles, p)
        keep = any(ctx.needs_input_grad[:3]) and 2 * layout.padded_evaluations <= cache_elements
        cache = []
        for tiles, start, k in zip(layout.tile_ids, layout.starts, layout.ks):
            b = len(tiles)
            out[tiles], saved = _chunk_forward(
                coef[start : start + b * k].view(b, k, 6), basis, feat[start : start + b * k].view(b, k, -1), background
            )
            out_alpha[tiles] = 1.0 - saved[3]
            if keep:
                cache.append(saved)
        ctx.layout = layout
        ctx.cache = cache if keep else None
        ctx.save_for_backward(coef, feat, background)
        return out, out_alpha

    @staticmethod
    def backward(ctx, grad_out, grad_alpha):
        coef, feat, background = ctx.saved_tensors
        layout: TileLayout = ctx.layout
        basis = tile_basis(layout.tile_size, coef.dtype)
        grad_coef = torch.zeros_like(coef)
        grad_feat = torch.zeros_like(feat)
        grad_bg = torch.zeros_like(background)
        covered = torch.zeros(layout.num_tiles, dtype=torch.bool)
        for c, (tiles, start, k) in enumerate(zip(layout.tile_ids, layout.starts, layout.ks)):
            b = len(tiles)
            f = feat[start : start + b * k].view(b, k, -1)
            if ctx.cache is not None:
                weight, ratio, unclamped, t_final = ctx.cache[c]
            else:
                _, (weight, ratio, unclamped, t_final) = _chunk_forward(
                    coef[start : start + b * k].view(b, k, 6), basis, f, background
                )
            g_out = grad_out[tiles]  # [b, P, F]
            wg = weight * torch.matmul(f, g_out.transpose(1, 2))  # w_k g_k, [b, K, P]
            # The background enters through T_N, and so does the alpha output 1 - T_N.
            total = (
                wg.sum(dim=1, keepdim=True)
                + (t_final * (torch.matmul(g_out, background) - grad_alpha[tiles]))[:, None, :]
            )
            suffix = torch.sub(total, torch.cumsum(wg, dim=1))  # S_k
            d_s = torch.addcmul(wg, suffix, ratio, value=-1.0).mul_(unclamped)  # -dL/ds
            grad_coef[start : start + b * k] = torch.matmul(d_s, basis.T).neg_().reshape(b * k, 6)
            grad_feat[start : start + b * k] = torch.matmul(weight, g_out).reshape(b * k, -1)
            grad_bg += torch.einsum("bp,bpf->f", t_final, g_out)
            covered[tiles] = True
        grad_bg += grad_out[~covered].sum(dim=(0, 1))
        ctx.cache = None
        return grad_coef, grad_feat, grad_bg, None, None


def composite(
    coef: torch.Tensor,
    feat: torch.Tensor,
    background: torch.Tensor,
    layout: TileLayout,
    width: int,
    height: int,
    *,
    cache_elements: int = 1 << 27,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite per-pair features into an image.

    Args:
        coef: ``[L, 6]`` from :func:`pair_coefficients`.
        feat: ``[L, F]`` per padded pair features (e.g. rgb, depth).
        background: ``[F]`` value where nothing covers a pixel.
        cache_elements: float32 values the forward may keep for the backward (default 512 MiB).
    Returns:
        ``features [height, width, F]`` and ``alpha [height, width]`` (1 - final transmittance).
    """
    tiles, alpha = _Composite.apply(coef, feat, background, layout, cache_elements)
    t, f = layout.tile_size, feat.shape[1]
    img = tiles.view(layout.tiles_y, layout.tiles_x, t, t, f).permute(0, 2, 1, 3, 4)
    alpha = alpha.view(layout.tiles_y, layout.tiles_x, t, t).permute(0, 2, 1, 3)
    rows, cols = layout.tiles_y * t, layout.tiles_x * t
    return img.reshape(rows, cols, f)[:height, :width], alpha.reshape(rows, cols)[:height, :width]
