"""Shared fixtures: synthetic scenes with ground truth, the simulated model, tiny models."""

from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
MODELS = REPO / "models"


@pytest.fixture(scope="session")
def demo_cache(tmp_path_factory):
    """A private FFRECON_CACHE so tests never read or write the user's cache."""
    return tmp_path_factory.mktemp("ffrecon-cache")


@pytest.fixture(scope="session")
def small_demo(demo_cache):
    """8 frames at 224x168 with the simulated model (fast): DemoInputs."""
    import os

    from ffrecon.demo import DemoOptions, prepare_demo
    from ffrecon.synthetic import SceneOptions

    os.environ["FFRECON_CACHE"] = str(demo_cache)
    return prepare_demo(DemoOptions(scene=SceneOptions(num_frames=8, width=224, height=168, seed=1)))


@pytest.fixture(scope="session")
def demo12(demo_cache):
    """12 frames at 320x240 with the simulated model: COLMAP registers them all, so every stage runs."""
    import os

    from ffrecon.demo import DemoOptions, prepare_demo
    from ffrecon.synthetic import SceneOptions

    os.environ["FFRECON_CACHE"] = str(demo_cache)
    return prepare_demo(DemoOptions(scene=SceneOptions(num_frames=12, width=320, height=240, seed=1)))


@pytest.fixture
def one_torch_thread():
    """torch on one thread: on a shared 2-core machine two OpenMP threads can run ten times slower
    than one whenever the other core is busy (measured by the splat and alignment tests)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
