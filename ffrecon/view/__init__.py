"""``ffrecon view OUT``: an interactive browser viewer (viser) of an output folder's cameras, points and splat."""

from ffrecon.view.scene import Estimate, ViewOptions, ViewScene, load_scene

__all__ = ["Estimate", "PortInUse", "ViewOptions", "ViewScene", "Viewer", "load_scene", "start_viewer"]


def __getattr__(name: str):
    """The server's names, imported on first use: it loads torch and the splat's kernels, and the report reads
    scenes through :mod:`ffrecon.view.scene` in every run."""
    if name in ("PortInUse", "Viewer", "start_viewer"):
        from ffrecon.view import server

        return getattr(server, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
