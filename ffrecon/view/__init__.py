"""``ffrecon view OUT``: an interactive browser viewer (viser) of an output folder's cameras, points and splat."""

from ffrecon.view.scene import Estimate, ViewOptions, ViewScene, load_scene
from ffrecon.view.server import PortInUse, Viewer, start_viewer

__all__ = ["Estimate", "PortInUse", "ViewOptions", "ViewScene", "Viewer", "load_scene", "start_viewer"]
