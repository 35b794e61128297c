"""report.html's building blocks: the page's style, tables, figures and galleries of embedded (base64) images."""

from __future__ import annotations

import base64
import html
from pathlib import Path

import cv2
import numpy as np

from ffrecon.report.plots import thumbnail_png

MAX_THUMBNAILS = 12


CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;
color:#222}
h1{margin-bottom:.2em} h2{border-bottom:1px solid #ddd;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;margin:.6em 0}
td,th{border:1px solid #ddd;padding:.25em .6em;text-align:left;font-size:.92em}
th{background:#f5f5f5} .pass{color:#137333;font-weight:600} .fail{color:#c5221f;font-weight:600}
.skipped{color:#80868b;font-weight:600} .reused{color:#1a73e8;font-weight:600}
.banner{padding:.7em 1em;border-radius:6px;margin:.8em 0} .ok{background:#e6f4ea} .bad{background:#fce8e6}
.warn{background:#fef7e0}
.gallery{display:flex;flex-wrap:wrap;gap:.5em} .gallery figure{margin:0;font-size:.8em;text-align:center}
img{max-width:100%} .muted{color:#666;font-size:.9em} .scroll{overflow-x:auto} .g3 figure{width:32%}
.g3 img{width:100%} .flagged img{outline:4px solid #c5221f;outline-offset:-4px} .flagged figcaption{color:#c5221f}
"""


SIMULATED = (
    "<div class='banner warn'><b>Simulated model.</b> The feed-forward cameras and depth come from ffrecon's "
    "simulated model (ground truth plus injected error), not a trained network. Numbers show the pipeline "
    "working, not a model's accuracy.</div>"
)


def field_default(options_class, name: str):
    """A field's default, read from its options dataclass (captions name it, never a copy of it)."""
    return options_class.__dataclass_fields__[name].default


def ordinal(n: int) -> str:
    """``"8th"``, ``"1st"``, ``"22nd"``.

    >>> [ordinal(n) for n in (1, 2, 3, 4, 8, 11, 12, 13, 21, 22)]
    ['1st', '2nd', '3rd', '4th', '8th', '11th', '12th', '13th', '21st', '22nd']
    """
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


def fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if v is None or v == [] or v == "":
        return "—"
    if isinstance(v, list):
        return html.escape(", ".join(str(x) for x in v))
    return html.escape(str(v))


def cell(key: str, value) -> str:
    if key == "status" and isinstance(value, str):
        return f'<span class="{value.lower()}">{html.escape(value)}</span>'
    return fmt(value)


def table(rows: list[dict]) -> str:
    if not rows:
        return ""
    keys = list(dict.fromkeys(k for r in rows for k in r))
    head = "".join(f"<th>{html.escape(k)}</th>" for k in keys)
    body = "".join("<tr>" + "".join(f"<td>{cell(k, r.get(k))}</td>" for k in keys) + "</tr>" for r in rows)
    return f"<div class='scroll'><table><tr>{head}</tr>{body}</table></div>"


def img(png: bytes, alt: str) -> str:
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{base64.b64encode(png).decode()}">'


def figure(title: str, png: bytes, caption: str) -> str:
    return f"<figure>{img(png, title)}<figcaption class='muted'>{html.escape(caption)}</figcaption></figure>"


def gallery(items: list[tuple[str, bytes]], wide: bool = False, flagged: frozenset[str] = frozenset()) -> str:
    """Thumbnails with captions; those whose caption is in ``flagged`` are framed in red."""
    if not items:
        return ""
    figures = "".join(
        f"<figure{' class=flagged' if cap in flagged else ''}>{img(png, cap)}"
        f"<figcaption>{html.escape(cap)}</figcaption></figure>"
        for cap, png in items
    )
    return f"<div class='gallery{' g3' if wide else ''}'>{figures}</div>"


def read_rgb(path: Path) -> np.ndarray | None:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    return None if bgr is None else cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def thumb(path: Path, caption: str, max_side: int) -> list[tuple[str, bytes]]:
    rgb = read_rgb(path)
    return [] if rgb is None else [(caption, thumbnail_png(rgb, max_side=max_side))]


def depth_preview(depth: np.ndarray) -> np.ndarray:
    """A colour-mapped depth map (near = bright) for people; unknown pixels black."""
    valid = depth > 0
    out = np.zeros(depth.shape + (3,), np.uint8)
    if valid.any():
        lo, hi = np.quantile(depth[valid], [0.02, 0.98])
        norm = np.clip((hi - depth) / max(hi - lo, 1e-9), 0, 1)
        colour = cv2.applyColorMap((norm * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
        out[valid] = cv2.cvtColor(colour, cv2.COLOR_BGR2RGB)[valid]
    return out


def every(items: list, limit: int = MAX_THUMBNAILS) -> list:
    return items[:: max(1, len(items) // limit)][:limit]
