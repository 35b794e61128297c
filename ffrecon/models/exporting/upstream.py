"""Import upstream model code (VGGT, DUSt3R, MASt3R, Pi3, Depth Anything 3) for export.

The upstream repositories are not Python distributions ffrecon can depend on: users clone them (or,
for Depth Anything 3, ``pip install --no-deps depth-anything-3``). Their READMEs say to put the
clone's root on ``sys.path``; :func:`import_upstream` does exactly that, once, for the folder the
user names with ``--upstream`` (and only then), so the code is imported as shipped, never copied.
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path
from types import ModuleType

from ffrecon.errors import InputError

# Where each family's package sits inside a clone, and how a user gets the code.
WHERE = {
    "vggt": ("vggt", "git clone https://github.com/facebookresearch/vggt, then --upstream vggt"),
    "dust3r": ("dust3r", "git clone --recursive https://github.com/naver/dust3r, then --upstream dust3r"),
    "mast3r": ("mast3r", "git clone --recursive https://github.com/naver/mast3r, then --upstream mast3r"),
    "pi3": ("pi3", "git clone https://github.com/yyfz/Pi3, then --upstream Pi3"),
    "depth_anything_3": ("depth_anything_3", "pip install --no-deps depth-anything-3==0.1.1 einops omegaconf addict"),
}


def import_upstream(module: str, upstream: Path | None, *, family: str) -> ModuleType:
    """Import ``module`` (e.g. ``"vggt.models.vggt"``) from the clone ``upstream`` or the environment.

    Args:
        module: dotted module name inside the upstream package.
        upstream: the clone's root folder (the one holding the package folder), or None to use an
            installed package.
        family: key of :data:`WHERE`, for the error message.
    Raises:
        InputError: the folder does not hold the package, or nothing importable was found.
    """
    package, how = WHERE[family]
    if upstream is not None:
        root = Path(upstream).expanduser().resolve()
        if not (root / package).is_dir():
            raise InputError(
                f"--upstream {upstream} does not hold the '{package}' package folder",
                f"pass the root of the upstream clone ({how})",
            )
        if str(root) not in sys.path:
            sys.path.insert(0, str(root))  # the upstream README's own instruction (see the module docstring)
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        missing = getattr(exc, "name", None) or str(exc)
        if missing and not missing.startswith(package):
            raise InputError(
                f"the upstream {family} code needs the Python package '{missing}', which is not installed",
                "pip install 'ffrecon[export]' (huggingface_hub, einops, safetensors, ...)",
            ) from exc
        raise InputError(
            f"the upstream {family} code was not found ({exc})", f"{how}; or pass --upstream DIR with the clone's root"
        ) from exc
