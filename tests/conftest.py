"""Shared fixtures: synthetic scenes with ground truth, the simulated model, tiny models."""

import shutil
import signal
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
MODELS = REPO / "models"
CLIENTS = REPO / "clients"  # the npm package of web clients the outputs are tested in (make clients)


def ctrl_c_default() -> None:
    """``preexec_fn`` of a command a test stops with SIGINT: the signal's default action, as a terminal's Ctrl-C
    finds it. A shell without job control starts a background job (``bash .ci/run > log &``) with SIGINT ignored,
    every process under it inherits that, and Python then installs no Ctrl-C handler: such a command ran on
    through the SIGINT (both Ctrl-C tests failed in CI runs started in the background; reproduced in 4 of 4)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


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


@pytest.fixture(scope="session")
def chromium() -> Path:
    """Debian's Chromium, run headless by the web-client tests; skipped with the reason when absent."""
    path = shutil.which("chromium") or shutil.which("chromium-browser")
    if path is None:
        pytest.skip("headless Chromium is not installed: `make clients` installs Debian's chromium")
    return Path(path)


@pytest.fixture(scope="session")
def node_clients() -> Path:
    """``clients/node_modules`` (splat-transform, Spark, three, puppeteer-core); skipped when not installed."""
    if shutil.which("node") is None:
        pytest.skip("node is not installed (apt-get install nodejs npm), so the npm clients cannot run")
    if not (CLIENTS / "node_modules" / ".ffrecon-installed").exists():
        pytest.skip("the npm clients are not installed: run `make clients` (npm ci in clients/)")
    return CLIENTS / "node_modules"


@pytest.fixture(scope="session")
def full_run(tmp_path_factory, demo12):
    """A complete output folder of 12 frames at 320x240 with every stage (feed-forward, COLMAP, refined,
    points, a briefly trained splat and its exports): what viewers and web clients open."""
    from ffrecon.pipeline import RunOptions, run
    from ffrecon.splat.optimize import OptimizeOptions
    from ffrecon.splat.stage import SplatOptions

    out = tmp_path_factory.mktemp("full-run") / "out"
    splat = SplatOptions(video_frames=12, optimize=OptimizeOptions.brief(max_seconds=8.0, iterations=300))
    result = run(demo12.images, out, demo12.model, RunOptions(splat=splat, ground_truth=demo12.scene_dir))
    assert result.exit_code == 0, f"the run failed with exit code {result.exit_code}"
    return out
