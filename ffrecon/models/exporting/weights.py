"""Loading the checkpoints users download (state dicts in .pt/.pth/.bin/.safetensors, or a folder of one)."""

from __future__ import annotations

import logging
from pathlib import Path

import torch

from ffrecon.errors import InputError

log = logging.getLogger("ffrecon.export_model")

WEIGHT_SUFFIXES = (".safetensors", ".pt", ".pth", ".bin", ".ckpt")


def find_weights(path: Path) -> Path:
    """The weight file itself, or the single weight file inside a downloaded folder."""
    path = Path(path).expanduser()
    if path.is_file():
        return path
    if path.is_dir():
        found = sorted(p for p in path.iterdir() if p.suffix in WEIGHT_SUFFIXES)
        if len(found) == 1:
            return found[0]
        if found:
            preferred = [p for p in found if p.suffix == ".safetensors"] or found
            log.info("%s holds %d weight files; using %s", path, len(found), preferred[0].name)
            return preferred[0]
    raise InputError(
        f"no checkpoint at {path}",
        f"pass a weight file ({', '.join(WEIGHT_SUFFIXES)}) or the folder you downloaded it into",
    )


def load_state_dict(path: Path) -> dict[str, torch.Tensor]:
    """A flat ``name -> tensor`` dict from a checkpoint file or folder (common wrappers unpacked)."""
    file = find_weights(Path(path))
    try:
        if file.suffix == ".safetensors":
            from safetensors.torch import load_file

            state = load_file(str(file))
        else:
            state = torch.load(file, map_location="cpu", weights_only=True)
    except Exception as exc:  # corrupt files raise several types
        raise InputError(
            f"cannot read checkpoint {file}: {str(exc).splitlines()[0]}", "download the checkpoint again"
        ) from exc
    for key in ("model", "state_dict", "module"):  # training checkpoints wrap the weights
        if isinstance(state, dict) and isinstance(state.get(key), dict):
            state = state[key]
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise InputError(
            f"{file} is not a state dict of tensors", "pass the model weights, not a full training checkpoint"
        )
    return state


def load_into(
    model: torch.nn.Module,
    state: dict[str, torch.Tensor],
    *,
    ignore_prefixes: tuple[str, ...] = (),
    source: str = "checkpoint",
) -> None:
    """Load ``state`` strictly, except for keys under ``ignore_prefixes`` (heads ffrecon does not export)."""
    state = {
        k.removeprefix("module."): v
        for k, v in state.items()
        if not k.removeprefix("module.").startswith(ignore_prefixes)
    }
    result = model.load_state_dict(state, strict=False)
    missing = [k for k in result.missing_keys if not k.startswith(ignore_prefixes)]
    if missing or result.unexpected_keys:
        raise InputError(
            f"{source} does not fit this architecture: {len(missing)} missing keys (e.g. {missing[:3]}), "
            f"{len(result.unexpected_keys)} unexpected (e.g. {result.unexpected_keys[:3]})",
            "check that the checkpoint belongs to this family and size",
        )
