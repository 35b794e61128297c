"""Issue 25: on long captures the stored depth grids shrink to keep every frame's depth within a memory bound."""

import dataclasses

import numpy as np
import pytest

from ffrecon.models.multiview import MultiviewOptions, depth_side_within
from ffrecon.models.runner import OnnxModel
from ffrecon.models.stage import FeedForwardOptions, predict
from ffrecon.synthetic import SceneOptions, make_scene
from ffrecon.synthetic.simulated_model import SimulationOptions, build_simulated_vggt


@dataclasses.dataclass(frozen=True)
class _Capture:
    names: tuple[str, ...]


def test_depth_side_bound():
    options = MultiviewOptions(depth_memory_gb=1.0)
    assert depth_side_within(options, 250, 640, 480) == 1024  # 0.59 GB: the usual cap
    side = depth_side_within(options, 1000, 640, 480)
    assert 1000 * side * (side * 3 // 4) * 8 <= 2**30 < 1000 * (side + 2) * ((side + 2) * 3 // 4) * 8
    assert depth_side_within(MultiviewOptions(depth_memory_gb=None), 10**6, 640, 480) == 1024
    assert depth_side_within(MultiviewOptions(depth_memory_gb=1.0, max_depth_side=300), 1000, 640, 480) == 300


def test_a_tight_bound_stores_coarser_depth_and_keeps_the_cameras(tmp_path):
    scene = make_scene(SceneOptions(num_frames=12, width=224, height=168, seed=3))
    build_simulated_vggt(scene, path := tmp_path / "sim.onnx", SimulationOptions(seed=3))
    model, capture, images = OnnxModel(path, threads=1), _Capture(tuple(scene.names)), list(scene.images)
    chunks = MultiviewOptions(chunk_size=5, chunk_overlap=2)
    full = predict(model, capture, images, FeedForwardOptions(multiview=chunks))
    quarter = 12 * 224 * 168 * 8 / 4 / 2**30  # GB: half the side
    bounded = FeedForwardOptions(multiview=dataclasses.replace(chunks, depth_memory_gb=quarter))
    small = predict(model, capture, images, bounded)
    assert full.prediction.depth[0].shape == (168, 224) and full.chunks.max_depth_side == 1024
    assert small.prediction.depth[0].shape == (84, 112) and small.chunks.max_depth_side == 112
    assert small.chunks.to_report()["max_depth_side"] == 112
    assert (
        sum(d.nbytes + c.nbytes for d, c in zip(small.prediction.depth, small.prediction.depth_conf)) <= 2**30 * quarter
    )
    # The chunks are aligned on coarser depth: the cameras move by a hair.
    centres = [
        np.einsum("nij,ni->nj", p.cam_from_world[:, :, :3], -p.cam_from_world[:, :, 3])
        for p in (full.prediction, small.prediction)
    ]
    extent = np.ptp(centres[0], axis=0).max()
    assert np.abs(centres[1] - centres[0]).max() < 1e-3 * extent
    np.testing.assert_allclose(
        small.prediction.cam_from_world[:, :, :3], full.prediction.cam_from_world[:, :, :3], atol=1e-4
    )
    assert [c.fx for c in small.prediction.cameras] == pytest.approx([c.fx for c in full.prediction.cameras], rel=1e-4)
