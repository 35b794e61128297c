"""3D Gaussian splat PLY files in the standard 3DGS layout (docs/contracts.md).

Binary little-endian, one ``vertex`` element with float32 properties in this order:
``x y z nx ny nz f_dc_0..2 f_rest_0..f_rest_{3 * ((d + 1)^2 - 1) - 1} opacity scale_0..2 rot_0..3``.
Opacity is a logit, scales are logs, ``rot`` is a quaternion wxyz, ``f_rest`` is channel-major
(all red coefficients, then green, then blue). Normals are written as zeros, as 3DGS does.
The header is written by hand so that the file is exactly this layout and nothing else.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import torch

from ffrecon.errors import InputError
from ffrecon.splat.gaussians import Gaussians, num_sh_bases

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
    """Read a 3DGS PLY (binary little-endian, float properties, any order, extra properties ignored)."""
    path = Path(path)
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise InputError(f"{path} is not a PLY file", "pass a 3DGS splat .ply")
        names, count, fmt = [], None, None
        while True:
            line = f.readline()
            if not line:
                raise InputError(f"{path}: PLY header has no end_header", "the file is truncated or not a PLY")
            parts = line.decode("ascii", "replace").split()
            if not parts:
                continue
            if parts[0] == "format":
                fmt = parts[1]
            elif parts[0] == "element":
                if parts[1] != "vertex" or count is not None:
                    raise InputError(
                        f"{path}: unexpected element '{parts[1]}'", "a 3DGS splat PLY has one vertex element"
                    )
                count = int(parts[2])
            elif parts[0] == "property":
                if parts[1] not in ("float", "float32"):
                    raise InputError(
                        f"{path}: property {parts[-1]} is {parts[1]}, expected float",
                        "write the splat with float properties",
                    )
                names.append(parts[2])
            elif parts[0] == "end_header":
                break
        if fmt != "binary_little_endian" or count is None:
            raise InputError(
                f"{path}: format {fmt}, expected binary_little_endian with a vertex element",
                "re-export the splat in the 3DGS layout",
            )
        data = np.frombuffer(f.read(count * len(names) * 4), dtype="<f4").reshape(count, len(names))
    col = {name: i for i, name in enumerate(names)}

    def take(keys: list[str]) -> torch.Tensor:
        missing = [k for k in keys if k not in col]
        if missing:
            raise InputError(f"{path}: missing properties {missing}", "write the splat in the 3DGS layout")
        return torch.from_numpy(np.ascontiguousarray(data[:, [col[k] for k in keys]], dtype=np.float32))

    num_rest = sum(1 for name in names if name.startswith("f_rest_"))
    bases = num_rest // 3 + 1
    if num_rest % 3 or bases not in (1, 4, 9, 16):
        raise InputError(
            f"{path}: {num_rest} f_rest properties do not match an SH degree 0..3", "write 0, 9, 24 or 45 f_rest values"
        )
    dc = take(["f_dc_0", "f_dc_1", "f_dc_2"])[:, None, :]
    rest = take([f"f_rest_{i}" for i in range(num_rest)]).reshape(count, 3, bases - 1).transpose(1, 2)
    return Gaussians(
        means=take(["x", "y", "z"]),
        quats_wxyz=take(["rot_0", "rot_1", "rot_2", "rot_3"]),
        log_scales=take(["scale_0", "scale_1", "scale_2"]),
        opacity_logits=take(["opacity"])[:, 0].contiguous(),
        sh=torch.cat([dc, rest], dim=1).contiguous(),
    )
