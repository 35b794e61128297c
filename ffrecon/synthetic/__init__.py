"""Synthetic scenes with exact ground truth, and a simulated VGGT-contract model built from them.

Used by tests and by the demo (no real model weights can be downloaded in CI).
"""

from ffrecon.synthetic.scene import (
    CameraPath,
    SceneOptions,
    SyntheticScene,
    Texture,
    load_scene,
    make_scene,
    write_scene,
)

__all__ = ["CameraPath", "SceneOptions", "SyntheticScene", "Texture", "load_scene", "make_scene", "write_scene"]
