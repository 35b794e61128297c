"""Loop chunks: a model that drifts along its input, chunked over a closed orbit, and the loop pass that
closes the chain. Truth: the synthetic scene's cameras."""

import numpy as np
import pytest

from ffrecon.errors import InputError
from ffrecon.geometry.alignment import umeyama
from ffrecon.geometry.poses import camera_centers
from ffrecon.geometry.rotations import rotation_angle_deg
from ffrecon.models import loops
from ffrecon.models.loops import LoopOptions, owners
from ffrecon.models.multiview import ChunkLayout, MultiviewOptions, plan_chunks, predict_multiview_pass
from ffrecon.models.runner import MULTIVIEW_INPUT, OnnxModel
from ffrecon.report.html import _calls
from ffrecon.synthetic import SceneOptions, make_scene
from ffrecon.synthetic.simulated_model import SimulationOptions, build_simulated_vggt

DRIFT = 0.3  # deg per input slot: about 1.2 deg per link of 6-frame chunks sharing 2


@pytest.fixture(scope="module")
def drifting(tmp_path_factory):
    """48 frames once around the room, a model with small per-frame error and a drift along each call."""
    folder = tmp_path_factory.mktemp("drift")
    scene = make_scene(SceneOptions(num_frames=48, width=192, height=144, seed=4))
    errors = SimulationOptions(seed=4, rotation_noise_deg=0.3, translation_noise=0.005, drift_deg_per_slot=DRIFT)
    build_simulated_vggt(scene, folder / "drift.onnx", errors)
    return scene, OnnxModel(folder / "drift.onnx")


def _run(scene, model, loops: LoopOptions):
    infer = lambda batch: model.run({MULTIVIEW_INPUT: batch})  # noqa: E731
    options = MultiviewOptions(chunk_size=6, chunk_overlap=2, loops=loops)
    return predict_multiview_pass(list(scene.images), list(scene.names), infer, model.info(), options)


def _errors(prediction, scene) -> tuple[float, float, float]:
    """Degrees: the loop error (the first-to-last relative rotation against truth), then the median and the
    largest rotation error after the best Sim(3) on the camera centres."""
    est, ref = prediction.cam_from_world, scene.cam_from_world
    rel_est = est[-1, :, :3] @ est[0, :, :3].T
    rel_ref = ref[-1, :, :3] @ ref[0, :, :3].T
    loop = rotation_angle_deg((rel_est.T @ rel_ref)[None])[0]
    sim = umeyama(camera_centers(est), camera_centers(ref))  # truth_from_estimate
    per_frame = rotation_angle_deg(np.swapaxes(est[:, :, :3] @ sim.rotation.T, 1, 2) @ ref[:, :, :3])
    return float(loop), float(np.median(per_frame)), float(per_frame.max())


def test_loop_calls_close_a_drifting_chain(drifting):
    scene, model = drifting
    open_chain, none = _run(scene, model, LoopOptions(enabled=False))
    closed, loops = _run(scene, model, LoopOptions())
    assert none is None
    before, after = _errors(open_chain, scene), _errors(closed, scene)
    # Measured: loop 13.9 -> 2.8 deg, median 3.5 -> 0.7, largest 7.7 -> 2.5 (two loop calls used).
    assert before[0] > 8.0  # 12 links of about 1.2 deg: the revisit misses the start
    assert after[0] < 0.3 * before[0] and after[1] < 0.3 * before[1] and after[2] < 0.5 * before[2]
    assert loops.candidates >= 1 and any(c.used for c in loops.calls)
    used = [c for c in loops.calls if c.used]
    assert all(max(c.misfit) <= 0.05 for c in used) and max(c.closure_deg for c in used) > 5.0
    assert 1 <= loops.iterations <= 20 and loops.max_correction_deg > 5.0
    layout = ChunkLayout.of([[0, 5], [4, 9]], 6, 2, loops=loops).to_report()
    assert layout["loops"]["calls"][0]["frames"] and layout["loops"]["pose_graph_iterations"] == loops.iterations
    assert f"{len(used)} loop calls closed the chain" in _calls(layout)  # the HTML report's line


def test_no_drift_leaves_the_chain_where_it_was(tmp_path):
    """Without drift the loop calls agree with the chain: corrections stay at the noise of the fits."""
    scene = make_scene(SceneOptions(num_frames=30, width=160, height=120, seed=5))
    build_simulated_vggt(scene, tmp_path / "m.onnx", SimulationOptions(seed=5))
    model = OnnxModel(tmp_path / "m.onnx")
    plain, _ = _run(scene, model, LoopOptions(enabled=False))
    closed, loops = _run(scene, model, LoopOptions())
    assert loops is not None and any(c.used for c in loops.calls)
    assert loops.max_correction_deg < 0.1 and abs(np.log(loops.max_correction_scale)) < 0.01
    turn = rotation_angle_deg(np.swapaxes(closed.cam_from_world[:, :, :3], 1, 2) @ plain.cam_from_world[:, :, :3])
    assert turn.max() < 0.1


def test_owners_and_options():
    assert owners([[0, 1, 2, 3], [2, 3, 4, 5], [4, 5, 6]], 7).tolist() == [0, 0, 0, 0, 1, 1, 2]
    for bad in ({"min_chunk_gap": 1}, {"min_overlap": 0.0}, {"max_closure_deg": 0}, {"frames_per_end": 0}):
        with pytest.raises(InputError):
            LoopOptions(**bad)


def test_a_loop_call_the_model_fails_on_leaves_the_chunks_as_merged(drifting, monkeypatch):
    """A loop call whose outputs do not validate (the model returned NaN) is not the chunks' fault: the merged
    chunks stand, the run goes on, and the report says why no loop closed."""
    scene, model = drifting
    merged, _ = _run(scene, model, LoopOptions(enabled=False))
    real = model.run
    calls, chunks = [], len(plan_chunks(len(scene.images), 6, 2))

    def poisoned(inputs):
        out = real(inputs)
        if len(calls) >= chunks:  # the chunks pass; the loop calls come back with NaN cameras
            out = {k: np.full_like(v, np.nan) if k == "pose_enc" else v for k, v in out.items()}
        calls.append(len(inputs[MULTIVIEW_INPUT]))
        return out

    monkeypatch.setattr(model, "run", poisoned)
    kept, loops = _run(scene, model, LoopOptions())
    assert len(calls) > chunks and loops.calls == () and "non-finite" in loops.error.lower()
    np.testing.assert_array_equal(kept.cam_from_world, merged.cam_from_world)
    assert loops.to_report()["error"] == loops.error


def test_the_farthest_revisits_are_chosen_first(monkeypatch):
    """On a slow video chunks a few calls apart overlap more than the ends of a loop: the loop still wins,
    and no two chosen loops join the same stretches."""
    chunks = [list(range(4 * c, 4 * c + 6)) for c in range(10)]  # 10 chunks of 6 sharing 2: frames 0..41
    owner = owners(chunks, 42)
    keys = loops._key_frames(owner)
    chunk_of_key = owner[keys]
    overlap = np.eye(len(keys))
    for i, a in enumerate(chunk_of_key):
        for j, b in enumerate(chunk_of_key):
            if abs(int(a) - int(b)) == 3:
                overlap[i, j] = 0.9  # near neighbours: much in common
            elif {int(a), int(b)} in ({0, 9}, {1, 8}):
                overlap[i, j] = 0.5  # the revisits
    monkeypatch.setattr(loops, "overlap_matrix", lambda prediction: overlap)
    prediction = type("P", (), {"subset": lambda self, idx: None})()
    candidates, chosen = loops._revisits(prediction, owner, keys, LoopOptions(max_loops=3, min_chunk_gap=3))
    assert candidates == 7 + 2  # (0, 3) ... (6, 9), and the two revisits
    # (1, 8) is within 3 chunks of (0, 9) at both ends: the same stretches, left out; then the near pairs in
    # order, (1, 4) and (2, 5) left out beside (0, 3)
    assert [(a, b) for _, a, b, _, _ in chosen] == [(0, 9), (0, 3), (3, 6)]
