"""The demo: a synthetic scene with ground truth and a simulated VGGT-contract model.

No weights can be downloaded for the demo, so the "model" is ffrecon's simulated one: ground truth
plus controlled error (see :mod:`ffrecon.synthetic.simulated_model`). Every report says so.
Inputs are cached under ``$FFRECON_CACHE`` (default ``~/.cache/ffrecon``) and reused.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

from ffrecon.synthetic.scene import SceneOptions

log = logging.getLogger("ffrecon.demo")


@dataclass(frozen=True, kw_only=True)
class DemoOptions:
    scene: SceneOptions = field(default_factory=SceneOptions)  # 24 frames at 320x240 by default
    # Overrides of SimulationOptions fields; by default one frame is badly wrong, as real models
    # occasionally are, so the report shows how a disagreeing frame is caught.
    simulation: dict = field(default_factory=lambda: {"bad_frames": [7]})


@dataclass(frozen=True)
class DemoInputs:
    scene_dir: Path  # ground_truth.json, depth.npz
    images: Path  # scene_dir/images
    model: Path  # simulated ONNX model


def cache_dir() -> Path:
    return Path(os.environ.get("FFRECON_CACHE", Path.home() / ".cache" / "ffrecon"))


def prepare_demo(options: DemoOptions = DemoOptions()) -> DemoInputs:
    """Render the scene and build the simulated model once; later calls reuse them."""
    from ffrecon.synthetic import make_scene, write_scene
    from ffrecon.synthetic.simulated_model import SimulationOptions, build_simulated_vggt

    recipe = {"scene": options.scene.to_dict(), "simulation": options.simulation}
    key = hashlib.sha1(json.dumps(recipe, sort_keys=True).encode()).hexdigest()[:10]
    folder = cache_dir() / f"demo-{key}"
    model = folder / "simulated_vggt.onnx"
    if not (model.is_file() and (folder / "ground_truth.json").is_file()):
        log.info("preparing the demo scene and simulated model in %s", folder)
        scene = make_scene(options.scene)
        write_scene(scene, folder)
        tmp = model.with_suffix(".tmp")
        sim = {k: tuple(v) if isinstance(v, list) else v for k, v in options.simulation.items()}
        build_simulated_vggt(scene, tmp, SimulationOptions(seed=options.scene.seed, **sim))
        tmp.rename(model)
    return DemoInputs(folder, folder / "images", model)
