"""Issue 25: the model's chunks on Ray workers give the cameras of the local loop (a local Ray instance with
two CPU workers, as a cluster would run them), and Ray's failures read as ffrecon's."""

import dataclasses
import json
import sys

import numpy as np
import pycolmap
import pytest

from ffrecon.cli import main
from ffrecon.errors import InputError, ModelError
from ffrecon.models.distributed import RayOptions
from ffrecon.models.loops import LoopOptions
from ffrecon.models.multiview import MultiviewOptions
from ffrecon.models.runner import OnnxModel
from ffrecon.models.stage import FeedForwardOptions, predict
from ffrecon.synthetic import SceneOptions, make_scene
from ffrecon.synthetic.scene import write_scene
from ffrecon.synthetic.simulated_model import SimulationOptions, build_simulated_vggt
from tests.onnx_builders import vggt_like

ray = pytest.importorskip("ray", reason="Ray is not installed: pip install 'ffrecon[distributed]'")

# 12 frames: 4 calls, and a loop call between the first and the last (3 calls apart)
CHUNKS = FeedForwardOptions(
    multiview=MultiviewOptions(chunk_size=5, chunk_overlap=2, loops=LoopOptions(min_chunk_gap=3))
)


@dataclasses.dataclass(frozen=True)
class _Capture:  # what predict reads of a capture for a multi-view model
    names: tuple[str, ...]


@pytest.fixture(scope="module")
def scene_and_model(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ray")
    scene = make_scene(SceneOptions(num_frames=12, width=224, height=168, seed=3))
    build_simulated_vggt(scene, folder / "sim.onnx", SimulationOptions(seed=3, bad_frames=(5,)))
    return scene, folder / "sim.onnx"


@pytest.fixture(scope="module")
def _shutdown_ray():
    yield
    ray.shutdown()


@pytest.fixture
def local_ray(_shutdown_ray):
    """A local Ray instance with two CPUs, shared by the module's tests (predict leaves running an instance
    it did not start)."""
    if not ray.is_initialized():
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)


def test_ray_chunks_give_the_local_cameras(scene_and_model, local_ray):
    scene, path = scene_and_model
    model, capture, images = OnnxModel(path, threads=1), _Capture(tuple(scene.names)), list(scene.images)
    local = predict(model, capture, images, CHUNKS)
    on_ray = predict(model, capture, images, dataclasses.replace(CHUNKS, ray=RayOptions(workers=2)))
    assert on_ray.prediction.names == local.prediction.names
    np.testing.assert_allclose(on_ray.prediction.cam_from_world, local.prediction.cam_from_world, atol=1e-6)
    for a, b in zip(on_ray.prediction.depth, local.prediction.depth):
        np.testing.assert_allclose(a, b, rtol=1e-6)
    assert [c.fx for c in on_ray.prediction.cameras] == pytest.approx([c.fx for c in local.prediction.cameras])
    # The same four calls, spread over two worker processes.
    assert on_ray.chunks.frames == local.chunks.frames == ((0, 4), (3, 7), (6, 10), (9, 11))
    assert on_ray.chunks.engine == "ray" and local.chunks.engine == "local"
    assert len(set(on_ray.chunks.chunk_workers)) == 2 and on_ray.chunks.workers == 2
    # The loop pass ran its loop call on Ray too (the orbit's last chunk revisits the first) and came out the same.
    assert [c.frames for c in on_ray.chunks.loops.calls] == [c.frames for c in local.chunks.loops.calls]
    assert any(c.used for c in local.chunks.loops.calls)
    assert on_ray.chunks.loops.max_correction_deg == pytest.approx(local.chunks.loops.max_correction_deg, abs=1e-6)


def test_a_workers_model_error_reads_as_ffrecons(tmp_path, scene_and_model, local_ray):
    scene, _ = scene_and_model
    model = OnnxModel(vggt_like(tmp_path / "nan.onnx", fill=float("nan")), threads=1)
    capture, images = _Capture(tuple(scene.names)), list(scene.images)
    with pytest.raises(ModelError) as here:
        predict(model, capture, images, CHUNKS)
    with pytest.raises(ModelError) as there:
        predict(model, capture, images, dataclasses.replace(CHUNKS, ray=RayOptions(workers=2)))
    assert type(there.value) is type(here.value) and str(there.value) == str(here.value)


def test_what_ray_cannot_place_or_finish_stops_the_run_instead_of_waiting(scene_and_model, local_ray):
    """No GPU in the cluster for --ray-gpus: refused before any actor waits for one; no chunk back within
    ``wait_seconds``: a ModelError, not a hang."""
    scene, path = scene_and_model
    model, capture, images = OnnxModel(path, threads=1), _Capture(tuple(scene.names)), list(scene.images)
    with pytest.raises(InputError, match="0 GPUs: not enough") as caught:
        predict(model, capture, images, dataclasses.replace(CHUNKS, ray=RayOptions(gpus_per_worker=1.0)))
    assert "--ray-gpus" in caught.value.fix
    with pytest.raises(ModelError, match="no chunk finished on Ray within 0.001 s"):
        predict(model, capture, images, dataclasses.replace(CHUNKS, ray=RayOptions(workers=1, wait_seconds=0.001)))


def test_without_ray_installed_the_message_says_how(monkeypatch, scene_and_model):
    scene, path = scene_and_model
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    with pytest.raises(InputError, match=r"ffrecon\[distributed\]"):
        predict(
            OnnxModel(path),
            _Capture(tuple(scene.names)),
            list(scene.images),
            dataclasses.replace(CHUNKS, ray=RayOptions()),
        )


def test_run_with_ray_writes_the_local_runs_cameras_and_the_chunk_layout(tmp_path, scene_and_model):
    """``ffrecon run --ray``, starting its own local instance, against the same run without Ray."""
    scene, path = scene_and_model
    ray.shutdown()  # the run starts its own instance (and stops it)
    images = write_scene(scene, tmp_path / "scene")
    common = [
        "--model",
        str(path),
        "--no-colmap",
        "--no-refine",
        "--no-splat",
        "--chunk-size",
        "5",
        "--threads",
        "1",
        "-q",
    ]
    assert main(["run", str(images), "-o", str(tmp_path / "local"), *common]) == 0
    assert main(["run", str(images), "-o", str(tmp_path / "ray"), *common, "--ray", "--ray-workers", "2"]) == 0
    models = [pycolmap.Reconstruction(tmp_path / run / "sparse" / "0") for run in ("local", "ray")]
    for image in models[0].images.values():
        other = models[1].find_image_with_name(image.name)
        pose_a, pose_b = image.cam_from_world().matrix(), other.cam_from_world().matrix()
        np.testing.assert_allclose(pose_b, pose_a, atol=1e-6)
    report = json.loads((tmp_path / "ray" / "report.json").read_text())
    chunks = report["feedforward"]["chunks"]
    assert chunks["engine"] == "ray" and chunks["address"] == "local" and chunks["workers"] == 2
    assert chunks["calls"] == [[0, 4], [3, 7], [6, 10], [9, 11]] and not ray.is_initialized()


def test_no_cluster_at_the_address_is_an_input_error(scene_and_model):
    scene, path = scene_and_model
    ray.shutdown()
    options = dataclasses.replace(CHUNKS, ray=RayOptions(address="auto"))  # no Ray instance runs here
    with pytest.raises(InputError, match="cannot start or join Ray at auto") as caught:
        predict(OnnxModel(path), _Capture(tuple(scene.names)), list(scene.images), options)
    assert caught.value.exit_code == 2 and "ray status" in caught.value.fix
