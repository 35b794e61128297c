"""Procedural textures for the synthetic scenes.

Textures are float32 RGB images in [0, 1], sized in texels; the scene decides how many texels one
world unit of each surface gets. The rich texture is built for two consumers: SIFT wants distinctive,
non-repeating detail and the splat optimiser wants detail it can fit, so features span roughly 3 to
40 texels (smooth multi-octave value noise, soft-edged discs, rectangles, stripes and letters) and
there is no texel-level white noise.
"""

from __future__ import annotations

import functools
import string
from pathlib import Path

import cv2
import numpy as np

SHAPES_PER_TEXEL = 40 / 128**2  # shape density of the rich texture
_LETTERS = string.ascii_uppercase + string.digits


def value_noise(rng: np.random.Generator, height: int, width: int, cell_px: float, channels: int = 3) -> np.ndarray:
    """Smooth random field: a random lattice every ``cell_px`` texels, bicubically upsampled.

    Returns ``[height, width, channels]`` float32, roughly zero-mean with unit-ish spread.
    """
    gh, gw = int(np.ceil(height / cell_px)) + 3, int(np.ceil(width / cell_px)) + 3
    grid = rng.standard_normal((gh, gw, channels)).astype(np.float32)
    big = cv2.resize(grid, (int(round(gw * cell_px)), int(round(gh * cell_px))), interpolation=cv2.INTER_CUBIC)
    big = big.reshape(big.shape[0], big.shape[1], channels)
    oy, ox = int(cell_px), int(cell_px)  # skip the border cells, where bicubic clamps
    return big[oy : oy + height, ox : ox + width]


def _random_colour(rng: np.random.Generator) -> tuple[float, float, float]:
    """A saturated-ish random colour as an (r, g, b) tuple in [0, 1]."""
    hsv = np.array([[[rng.uniform(0, 180), rng.uniform(90, 255), rng.uniform(40, 255)]]], np.uint8)
    rgb = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0] / 255.0
    return tuple(float(c) for c in rgb)


def _draw_shapes(rng: np.random.Generator, img: np.ndarray, count: int) -> None:
    """Draw ``count`` random discs, rotated rectangles, stripe patches and letters into ``img`` (in place)."""
    h, w = img.shape[:2]
    for _ in range(count):
        kind = rng.integers(0, 4)
        colour = _random_colour(rng)
        cx, cy = float(rng.uniform(0, w)), float(rng.uniform(0, h))
        size = float(np.exp(rng.uniform(np.log(3.0), np.log(22.0))))
        if kind == 0:  # disc, possibly a ring
            thickness = -1 if rng.random() < 0.7 else max(2, int(size / 3))
            cv2.circle(img, (int(cx * 16), int(cy * 16)), int(size * 16), colour, thickness, cv2.LINE_AA, shift=4)
        elif kind == 1:  # rotated rectangle
            angle = rng.uniform(0, np.pi)
            half = np.array([size, size * rng.uniform(0.3, 1.0)])
            rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
            corners = (np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * half) @ rot.T + [cx, cy]
            cv2.fillPoly(img, [np.round(corners * 16).astype(np.int32)], colour, cv2.LINE_AA, shift=4)
        elif kind == 2:  # patch of parallel stripes
            angle = rng.uniform(0, np.pi)
            along = np.array([np.cos(angle), np.sin(angle)])
            across = np.array([-along[1], along[0]])
            gap = max(3.0, size / 3)
            for k in range(int(rng.integers(2, 5))):
                centre = np.array([cx, cy]) + across * gap * k
                p0, p1 = centre - along * size, centre + along * size
                cv2.line(
                    img,
                    tuple(np.round(p0 * 16).astype(int)),
                    tuple(np.round(p1 * 16).astype(int)),
                    colour,
                    max(1, int(gap / 2)),
                    cv2.LINE_AA,
                    shift=4,
                )
        else:  # a short random "word", drawn as a uint8 coverage mask (putText wants 8-bit images)
            text = "".join(rng.choice(list(_LETTERS), size=int(rng.integers(1, 4))))
            scale = size / 14.0 + 0.3
            thickness = max(1, int(round(scale * 2)))
            (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, thickness)
            pad = thickness + 2
            mask = np.zeros((th + base + 2 * pad, tw + 2 * pad), np.uint8)
            cv2.putText(mask, text, (pad, pad + th), cv2.FONT_HERSHEY_SIMPLEX, scale, 255, thickness, cv2.LINE_AA)
            x0, y0 = int(cx), int(cy)
            x1, y1 = min(w, x0 + mask.shape[1]), min(h, y0 + mask.shape[0])
            alpha = (mask[: y1 - y0, : x1 - x0].astype(np.float32) / 255.0)[..., None]
            region = img[y0:y1, x0:x1]
            region[...] = region * (1 - alpha) + np.asarray(colour, np.float32) * alpha


def rich_texture(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """Non-repeating multi-scale colour texture, ``[height, width, 3]`` float32 in [0, 1]."""
    base = np.array(_random_colour(rng), np.float32) * 0.6 + 0.2
    img = np.broadcast_to(base, (height, width, 3)).copy()
    for cell, amp in ((64.0, 0.22), (24.0, 0.16), (10.0, 0.10), (5.0, 0.06)):
        img += amp * value_noise(rng, height, width, cell)
    img = np.clip(img, 0.0, 1.0)
    _draw_shapes(rng, img, count=int(round(SHAPES_PER_TEXEL * height * width)) + 3)
    img = cv2.GaussianBlur(img, (0, 0), 0.7)  # soft edges, nothing at the texel level
    return np.clip(img, 0.02, 0.98)


def plain_texture(rng: np.random.Generator, height: int, width: int, *, contrast: float = 0.004) -> np.ndarray:
    """Near-uniform surface: one pale colour plus a very faint, very smooth variation."""
    base = np.array([0.62, 0.6, 0.57], np.float32) + rng.uniform(-0.01, 0.01, 3).astype(np.float32)
    img = base + contrast * value_noise(rng, height, width, 96.0)
    return np.clip(img, 0.0, 1.0).astype(np.float32)


def tile_texture(rng: np.random.Generator, tile_px: int) -> np.ndarray:
    """One square tile of rich texture that wraps seamlessly; ``[tile_px, tile_px, 3]`` float32."""
    big = rich_texture(rng, 2 * tile_px, 2 * tile_px)
    # Cross-fade the tile with its half-shifted copy so that opposite borders meet without a seam.
    ramp = np.abs(np.arange(tile_px) + 0.5 - tile_px / 2) / (tile_px / 2)  # 1 at borders, 0 in the middle
    a = big[:tile_px, :tile_px]
    b = np.roll(np.roll(big[tile_px:, tile_px:], tile_px // 2, 0), tile_px // 2, 1)
    weight = np.maximum(ramp[:, None], ramp[None, :])[..., None].astype(np.float32) ** 2
    return (a * (1 - weight) + b * weight).astype(np.float32)


@functools.lru_cache(maxsize=4)
def _photos(photo_dir: str) -> tuple[np.ndarray, ...]:
    """The photos in ``photo_dir`` (JPEG/PNG, sorted by name) as float32 RGB in [0, 1], read once."""
    paths = sorted(p for p in Path(photo_dir).iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    if not paths:
        raise ValueError(f"no JPEG or PNG photos in {photo_dir} to cut textures from")
    out = []
    for path in paths:
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is not None:
            out.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0)
    return tuple(out)


def photo_texture(rng: np.random.Generator, height: int, width: int, photo_dir: str) -> np.ndarray:
    """Crops of real photos from ``photo_dir`` (chosen and placed by ``rng``), side by side, resized to
    ``[height, width, 3]`` float32 in [0, 1]: real-world texture statistics (sky, repeated windows, blur)
    that procedural textures lack. A surface much wider than tall (a facade) gets one crop per 4:3 of its
    width, as buildings stand side by side. Rows are flipped: texture rows run up the walls (world z), so
    the photos stand upright there."""
    photos = _photos(photo_dir)
    pieces = max(1, int(round(width / height / (4 / 3))))
    edges = np.linspace(0, width, pieces + 1).round().astype(int)
    out = []
    for x_lo, x_hi in zip(edges[:-1], edges[1:]):
        photo = photos[int(rng.integers(len(photos)))]
        ph, pw = photo.shape[:2]
        aspect = (x_hi - x_lo) / height
        crop_w = min(pw, ph * aspect) * rng.uniform(0.5, 1.0)
        crop_h = crop_w / aspect
        x0, y0 = rng.uniform(0, pw - crop_w), rng.uniform(0, ph - crop_h)
        crop = photo[int(y0) : int(y0 + crop_h), int(x0) : int(x0 + crop_w)]
        out.append(cv2.resize(crop, (int(x_hi - x_lo), height), interpolation=cv2.INTER_AREA))
    return np.clip(np.concatenate(out, axis=1)[::-1], 0.02, 0.98).astype(np.float32)
