"""report.json (machines) and a self-contained report.html (people; opens offline).

Figures are PNG bytes embedded as base64, so the HTML file is one file that works anywhere.
"""

from __future__ import annotations

import base64
import html
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ffrecon.export.plots import thumbnail_png


@dataclass
class Figure:
    title: str
    png: bytes
    caption: str = ""


@dataclass
class ReportBuilder:
    """Collects the run's machine-readable record and the figures for people."""

    data: dict = field(default_factory=dict)
    figures: dict[str, list[Figure]] = field(default_factory=dict)  # section -> figures
    galleries: dict[str, list[tuple[str, bytes]]] = field(default_factory=dict)  # section -> (caption, png)

    def add_figure(self, section: str, figure: Figure) -> None:
        self.figures.setdefault(section, []).append(figure)

    def add_image(self, section: str, caption: str, rgb: np.ndarray, max_side: int = 240) -> None:
        self.galleries.setdefault(section, []).append((caption, thumbnail_png(rgb, max_side=max_side)))

    def write(self, out_dir: Path) -> tuple[Path, Path]:
        json_path = out_dir / "report.json"
        json_path.write_text(json.dumps(_jsonable(self.data), indent=2))
        html_path = out_dir / "report.html"
        html_path.write_text(render_html(self.data, self.figures, self.galleries))
        return json_path, html_path


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


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        return None if not math.isfinite(float(obj)) else float(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, Path):
        return str(obj)
    return obj


_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222}
h1{margin-bottom:.2em} h2{border-bottom:1px solid #ddd;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;margin:.6em 0} td,th{border:1px solid #ddd;padding:.25em .6em;text-align:left;font-size:.92em}
th{background:#f5f5f5} .pass{color:#137333;font-weight:600} .fail{color:#c5221f;font-weight:600} .skipped{color:#80868b;font-weight:600}
.banner{padding:.7em 1em;border-radius:6px;margin:.8em 0} .ok{background:#e6f4ea} .bad{background:#fce8e6} .warn{background:#fef7e0}
.gallery{display:flex;flex-wrap:wrap;gap:.5em} .gallery figure{margin:0;font-size:.8em;text-align:center} img{max-width:100%}
.muted{color:#666;font-size:.9em} .scroll{overflow-x:auto} .g3 figure{width:32%} .g3 img{width:100%}
"""


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if v is None or v == [] or v == "":
        return "—"
    if isinstance(v, list):
        return html.escape(", ".join(str(x) for x in v))
    return html.escape(str(v))


def _table(rows: list[dict]) -> str:
    if not rows:
        return ""
    keys = list(dict.fromkeys(k for r in rows for k in r))
    head = "".join(f"<th>{html.escape(k)}</th>" for k in keys)
    body = "".join("<tr>" + "".join(f"<td>{_cell(k, r.get(k))}</td>" for k in keys) + "</tr>" for r in rows)
    return f"<div class='scroll'><table><tr>{head}</tr>{body}</table></div>"


def _cell(key: str, value) -> str:
    if key == "status" and isinstance(value, str):
        return f'<span class="{value.lower()}">{html.escape(value)}</span>'
    return _fmt(value)


def _img(png: bytes, alt: str) -> str:
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{base64.b64encode(png).decode()}">'


def _feedforward_rows(ff: dict) -> list[dict]:
    """What the model's cameras mean: world frame, decoding assumptions, changes made at export."""
    rows = [
        ("world frame", ff.get("world_frame")),
        ("assumptions", ff.get("assumptions")),
        ("model notes", ff.get("model", {}).get("notes")),
        ("model", ff.get("model", {}).get("description")),
    ]
    return [{"item": k, "value": v} for k, v in rows if v]


def render_html(data: dict, figures: dict[str, list[Figure]], galleries: dict[str, list[tuple[str, bytes]]]) -> str:
    """The whole page: verdict banner, summary, then one section per stage with figures and tables."""
    parts = [
        f"<!doctype html><html><head><meta charset='utf-8'><title>ffrecon report</title><style>{_CSS}</style></head><body>"
    ]
    parts.append(
        f"<h1>ffrecon report</h1><p class='muted'>{_fmt(data.get('created'))} · ffrecon {_fmt(data.get('ffrecon_version'))} · input {_fmt(data.get('inputs', {}).get('source'))}</p>"
    )
    verdict = data.get("verdict", {})
    ok = verdict.get("status") == "ok"
    parts.append(
        f"<div class='banner {'ok' if ok else 'bad'}'><b>{html.escape(verdict.get('status', '?').upper())}</b> — {html.escape(verdict.get('message', ''))}</div>"
    )
    model = data.get("feedforward", {}).get("model", {})
    if model.get("simulated"):
        parts.append(
            "<div class='banner warn'><b>Simulated model.</b> The feed-forward cameras and depth come from ffrecon's simulated model (ground truth plus injected error), not a trained network. Numbers show the pipeline working, not a model's accuracy.</div>"
        )
    for item in data.get("skipped_stages", []):
        parts.append(
            f"<div class='banner warn'>Skipped <b>{html.escape(item['stage'])}</b>: {html.escape(item['reason'])}</div>"
        )
    summary = data.get("summary_rows", [])
    if summary:
        parts.append("<h2>Summary</h2>" + _table(summary))
    sections = [
        ("capture", "Capture", data.get("capture_flags", [])),
        ("feedforward", "Feed-forward cameras and depth", _feedforward_rows(data.get("feedforward", {}))),
        ("gates", "Verification gates", data.get("gates", [])),
        ("poses", "Pose error", data.get("pose_error_rows", [])),
        ("refine", "Refinement", data.get("refine_rows", [])),
        ("splat", "Gaussian splat", data.get("splat_rows", [])),
        ("timings", "Timings", data.get("timing_rows", [])),
    ]
    for key, title, rows in sections:
        figs, gallery = figures.get(key, []), galleries.get(key, [])
        if not (rows or figs or gallery):
            continue
        parts.append(f"<h2>{html.escape(title)}</h2>")
        parts.append(_table(rows))
        for fig in figs:
            parts.append(
                f"<figure>{_img(fig.png, fig.title)}<figcaption class='muted'>{html.escape(fig.caption or fig.title)}</figcaption></figure>"
            )
        if gallery:
            parts.append(
                f"<div class='gallery{' g3' if key == 'splat' else ''}'>"
                + "".join(
                    f"<figure>{_img(png, cap)}<figcaption>{html.escape(cap)}</figcaption></figure>"
                    for cap, png in gallery
                )
                + "</div>"
            )
    parts.append("<h2>Files</h2>" + _table([{"file": k, "path": v} for k, v in data.get("outputs", {}).items()]))
    parts.append("<p class='muted'>Full machine-readable record: report.json</p></body></html>")
    return "".join(parts)


def timings_png(timings: dict[str, float]) -> bytes:
    """Horizontal bars of seconds per stage (matplotlib Agg, no global pyplot state)."""
    import io

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure as MplFigure

    names = list(timings)
    fig = MplFigure(figsize=(6.0, 0.45 * len(names) + 0.9))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.barh(names[::-1], [timings[n] for n in names][::-1], color="#1f77b4")
    for y, n in enumerate(names[::-1]):
        ax.annotate(
            f"{timings[n]:.1f} s", (timings[n], y), xytext=(4, 0), textcoords="offset points", va="center", fontsize=8
        )
    ax.set_xlabel("seconds")
    ax.set_title("Time per stage", fontsize=10)
    ax.margins(x=0.15)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return buf.getvalue()
