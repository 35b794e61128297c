"""3D Gaussian splat PLY files in the standard 3DGS layout (docs/contracts.md).

Binary little-endian, one ``vertex`` element with float32 properties in this order:
``x y z nx ny nz f_dc_0..2 f_rest_0..f_rest_{3 * ((d + 1)^2 - 1) - 1} opacity scale_0..2 rot_0..3``.
Opacity is a logit, scales are logs, ``rot`` is a quaternion wxyz, ``f_rest`` is channel-major
(all red coefficients, then green, then blue). Normals are written as zeros, as 3DGS does.
The header is written by hand so that the file is exactly this layout and nothing else; reading goes
through gsply (a dependency already, for SPZ), which also takes other writers' property order and extras.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import gsply
import numpy as np
import torch

from ffrecon.errors import InputError
from ffrecon.gaussians import Gaussians, num_sh_bases

logger = logging.getLogger("ffrecon.splat")


def splat_property_names(sh_degree: int) -> list[str]:
    """The standard property list for SH degree ``sh_degree``.

    >>> splat_property_names(0)[:9]
    ['x', 'y', 'z', 'nx', 'ny', 'nz', 'f_dc_0', 'f_dc_1', 'f_dc_2']
    >>> splat_property_names(0)[9:]
    ['opacity', 'scale_0', 'scale_1', 'scale_2', 'rot_0', 'rot_1', 'rot_2', 'rot_3']
    >>> len(splat_property_names(3))
    62
    """
    rest = 3 * (num_sh_bases(sh_degree) - 1)
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def splat_to_array(gaussians: Gaussians, sh_degree: int | None = None) -> np.ndarray:
    """``[N, P]`` float32 rows in the property order of :func:`splat_property_names`.

    ``sh_degree`` pads (zeros) or truncates the SH bands; default: the splat's own degree.
    """
    degree = gaussians.sh_degree if sh_degree is None else sh_degree
    g = gaussians.with_sh_degree(degree)
    n = len(g)
    sh = g.sh.detach().cpu().float().numpy()  # [N, B, 3]
    rest = np.ascontiguousarray(sh[:, 1:].transpose(0, 2, 1)).reshape(n, -1)  # channel-major
    quats = torch.nn.functional.normalize(g.quats_wxyz.detach().float(), dim=1).cpu().numpy()
    cols = [
        g.means.detach().cpu().float().numpy(),
        np.zeros((n, 3), np.float32),
        sh[:, 0],
        rest,
        g.opacity_logits.detach().cpu().float().numpy()[:, None],
        g.log_scales.detach().cpu().float().numpy(),
        quats,
    ]
    return np.concatenate(cols, axis=1).astype("<f4")


def write_splat_ply(path: Path, gaussians: Gaussians, *, sh_degree: int | None = None) -> Path:
    """Write ``gaussians`` to ``path`` (atomically: a temporary file renamed into place)."""
    degree = gaussians.sh_degree if sh_degree is None else sh_degree
    data = splat_to_array(gaussians, degree)
    if not np.isfinite(data).all():
        raise ValueError(f"splat has {int((~np.isfinite(data)).sum())} non-finite values; refusing to write {path}")
    names = splat_property_names(degree)
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(data)}"]
    header += [f"property float {name}" for name in names]
    header += ["end_header"]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(np.ascontiguousarray(data).tobytes())
    os.replace(tmp, path)
    logger.info("wrote %s: %d Gaussians, SH degree %d", path, len(data), degree)
    return path


def read_splat_ply(path: Path) -> Gaussians:
    """Read a 3DGS PLY (SH degree 0-3) with gsply, the PLY reader already among ffrecon's dependencies.

    Values are taken as stored (log-scales, opacity logits, SH coefficients, wxyz quaternions). A file
    that is not a 3DGS splat PLY raises :class:`InputError`.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path} does not exist", "pass the path of a 3DGS splat .ply")
    try:
        data = gsply.plyread(path)
    except Exception as exc:  # gsply raises ValueError, KeyError, struct and numpy errors for malformed files
        raise InputError(
            f"{path} is not a readable 3DGS splat PLY ({type(exc).__name__}: {exc})",
            "pass a binary little-endian PLY in the 3DGS layout (x y z, f_dc_*, f_rest_*, opacity, scale_*, rot_*)",
        ) from exc
    if data.is_scales_linear or data.is_opacities_linear or data.is_sh0_rgb:
        raise InputError(f"{path}: gsply read activated values", "write the splat in the 3DGS layout (raw values)")

    def tensor(array) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(np.asarray(array, dtype=np.float32)))

    sh_rest = data.shN if data.shN is not None and np.size(data.shN) else np.zeros((len(data.means), 0, 3))
    sh = np.concatenate([np.asarray(data.sh0, np.float32)[:, None, :], np.asarray(sh_rest, np.float32)], axis=1)
    return Gaussians(
        means=tensor(data.means),
        quats_wxyz=tensor(data.quats),
        log_scales=tensor(data.scales),
        opacity_logits=tensor(np.asarray(data.opacities).reshape(-1)),
        sh=tensor(sh),
    )
