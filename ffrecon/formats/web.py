"""Web-ready splats: Niantic's SPZ (through gsply) and PlayCanvas's SOG (through splat-transform).

**SPZ and coordinate frames.** Niantic's README says SPZ data is "by default" RUB (OpenGL) and that
callers declare their own frame when packing; but its own ``ply_to_spz`` tool packs a 3DGS PLY with
``UNSPECIFIED`` frames (no conversion), splat-transform decodes SPZ "RAW (CoordinateSystem
UNSPECIFIED)" into the same frame as a PLY, and Spark's Rust decoder converts nothing either. So the
bytes are written in the PLY's own frame, ffrecon's OpenCV world (x, y, z as in ``splat.ply``), and
every one of those readers then places each Gaussian where ``splat.ply`` does (checked by
``tests/formats/test_web_clients.py``, which renders both in Spark from a training camera).

**SPZ quantisation** (version 3, gzip, as gsply writes it; the round trip is tested against these):

- position: 24-bit signed fixed point with ``fractional_bits`` (12, or fewer when the scene is larger
  than +-2048 units): error <= 2 ** -(fractional_bits + 1), 0.000122 units at 12 bits;
- log-scale: ``round((s + 10) * 16)`` in a byte, error <= 1/32, clipped to [-10, 5.9375];
- opacity: ``round(sigmoid(logit) * 255)``, error <= 0.5 / 255 in opacity;
- SH DC: ``round(dc * 0.15 * 255 + 127.5)``, error <= 0.5 / (0.15 * 255) = 0.0131 in the coefficient
  (0.0037 in colour), clipped to +-3.33;
- SH rest: ``round(c * 128 + 128)``, error <= 1/256, clipped to [-1, 0.9922];
- rotation: smallest-three, 9 bits per component: about 0.0014 per quaternion component (sign free).
"""

from __future__ import annotations

import logging
import os
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import torch

from ffrecon.errors import FFReconError
from ffrecon.gaussians import Gaussians

logger = logging.getLogger("ffrecon.export")

SPZ_VERSION = 3  # gzip container: read by Spark, splat-transform, Niantic's library and older viewers
SPZ_MAX_FRACTIONAL_BITS = 12  # Niantic's default precision
SPLAT_TRANSFORM_ENV = "FFRECON_SPLAT_TRANSFORM"
REPO_SPLAT_TRANSFORM = Path(__file__).resolve().parents[2] / "clients" / "node_modules" / ".bin" / "splat-transform"


class WebExportError(FFReconError):
    """A web format could not be written (a converter missing, failing or too slow)."""


def spz_fractional_bits(means: np.ndarray) -> int:
    """The most fractional bits (at most 12) whose 24-bit fixed point still holds every coordinate.

    >>> spz_fractional_bits(np.array([[1.0, -3.0, 2000.0]]))
    12
    >>> spz_fractional_bits(np.array([[5000.0, 0.0, 0.0]]))
    10
    """
    extent = float(np.abs(means).max()) if len(means) else 0.0
    bits = SPZ_MAX_FRACTIONAL_BITS
    while bits > 0 and extent * (1 << bits) >= (1 << 23) - 1:
        bits -= 1
    if bits == 0:
        raise WebExportError(
            f"splat coordinates reach {extent:.3g}, beyond SPZ's 24-bit fixed point", "crop or rescale the splat"
        )
    return bits


def write_splat_spz(path: Path, gaussians: Gaussians, *, sh_degree: int | None = None) -> Path:
    """Write ``gaussians`` (world frame, as in ``splat.ply``) to a Niantic SPZ file (version 3, gzip).

    Positions keep the PLY's frame (see the module docstring); values beyond SPZ's byte ranges are
    clipped, and how many is logged. Written atomically (a temporary file renamed into place).
    """
    import gsply

    degree = gaussians.sh_degree if sh_degree is None else sh_degree
    g = gaussians.with_sh_degree(degree)
    sh = g.sh.float().cpu().numpy()  # [N, B, 3], band 0 = DC
    means = g.means.float().cpu().numpy()
    quats = torch.nn.functional.normalize(g.quats_wxyz.float(), dim=1).cpu().numpy()
    data = gsply.GSData.from_arrays(
        means=means,
        scales=g.log_scales.float().cpu().numpy(),
        quats=quats,
        opacities=g.opacity_logits.float().cpu().numpy(),
        sh0=np.ascontiguousarray(sh[:, 0]),
        shN=np.ascontiguousarray(sh[:, 1:]) if degree > 0 else None,
        format="ply",
    )
    _log_clipping(g, sh)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    gsply.write_spz(tmp, data, version=SPZ_VERSION, fractional_bits=spz_fractional_bits(means))
    os.replace(tmp, path)
    logger.info("wrote %s: %d Gaussians, SH degree %d (%.1f MB)", path, len(g), degree, path.stat().st_size / 1e6)
    return path


def _log_clipping(g: Gaussians, sh: np.ndarray) -> None:
    log_scales = g.log_scales.float().cpu().numpy()
    clipped = {
        "log-scales outside [-10, 5.94]": int(((log_scales < -10) | (log_scales > 5.9375)).sum()),
        "SH DC beyond +-3.33": int((np.abs(sh[:, 0]) > 0.5 / 0.15).sum()),
        "SH rest beyond [-1, 0.99]": int(((sh[:, 1:] < -1) | (sh[:, 1:] > 127 / 128)).sum()),
    }
    for what, count in clipped.items():
        if count:
            logger.info("splat.spz: %d %s clipped by SPZ's quantisation", count, what)


def find_splat_transform() -> Path | None:
    """PlayCanvas's ``splat-transform``: ``$FFRECON_SPLAT_TRANSFORM``, else on ``PATH``, else the repo's
    ``clients/node_modules/.bin`` (``make clients``); None when none is found."""
    if os.environ.get(SPLAT_TRANSFORM_ENV):
        return Path(os.environ[SPLAT_TRANSFORM_ENV])
    found = shutil.which("splat-transform")
    if found:
        return Path(found)
    return REPO_SPLAT_TRANSFORM if REPO_SPLAT_TRANSFORM.exists() else None


def write_sog(ply_path: Path, sog_path: Path, *, timeout_s: float = 600.0, executable: Path | None = None) -> Path:
    """Convert a 3DGS PLY to PlayCanvas's SOG with ``splat-transform -g cpu`` (a bounded subprocess).

    SOG's SH compression is a k-means on the CPU here, and its cost grows faster than the splat.
    Measured with splat-transform 3.7.0 on this project's 2-core machine, SH degree 3: with non-zero
    SH rest coefficients 3k Gaussians took 7 s, 12k took 101 s, 70k did not finish in 10 minutes;
    a brief CPU splat whose SH rest coefficients are still all zero took 4 s for 58k. Hence opt-in
    (``SplatOptions.sog``, ``--sog``) and ``timeout_s``. Raises :class:`WebExportError` naming the
    problem and the fix when the converter is missing, fails or runs out of time.
    """
    exe = executable or find_splat_transform()
    if exe is None or not Path(exe).exists():
        raise WebExportError(
            "SOG needs PlayCanvas's splat-transform, which was not found",
            f"run `make clients` (installs it under clients/node_modules), `npm i -g @playcanvas/splat-transform`, "
            f"or set {SPLAT_TRANSFORM_ENV} to its path",
        )
    sog_path = Path(sog_path)
    tmp = sog_path.with_name(sog_path.stem + ".tmp.sog")  # splat-transform picks the format by extension
    cmd = [str(exe), "-w", "-q", "-g", "cpu", str(ply_path), str(tmp)]
    start = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, check=False)
    except subprocess.TimeoutExpired as err:
        tmp.unlink(missing_ok=True)
        raise WebExportError(
            f"splat-transform did not finish the SOG in {timeout_s:.0f} s ({ply_path})",
            "SOG's CPU k-means grows with the splat: leave out --sog for large splats, or raise the timeout",
        ) from err
    except OSError as err:
        raise WebExportError(f"cannot run {exe}: {err}", "reinstall it with `make clients`") from err
    if proc.returncode != 0 or not tmp.exists() or tmp.stat().st_size == 0:
        tmp.unlink(missing_ok=True)
        detail = (proc.stderr or proc.stdout).strip()[-800:]
        raise WebExportError(
            f"splat-transform failed (exit {proc.returncode}) converting {ply_path} to SOG: {detail}",
            "check that node is at least version 18 and that splat.ply opens in splat-transform (--info)",
        )
    os.replace(tmp, sog_path)
    logger.info("wrote %s in %.1f s (%.1f MB)", sog_path, time.perf_counter() - start, sog_path.stat().st_size / 1e6)
    return sog_path
