"""The committed tiny ONNX fixtures: contract names, shapes, ranges, determinism, reproducible build."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest

from ffrecon.models.vggt import decode_pose_enc

REPO = Path(__file__).resolve().parents[2]
TINY_VGGT = REPO / "models" / "tiny_vggt.onnx"
TINY_DUST3R = REPO / "models" / "tiny_dust3r.onnx"


def _run(path: Path, feeds: dict) -> dict:
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return dict(zip([o.name for o in session.get_outputs()], session.run(None, feeds)))


def _images(seed: int, shape) -> np.ndarray:
    return np.random.default_rng(seed).random(shape, dtype=np.float32)


@pytest.mark.parametrize("path", [TINY_VGGT, TINY_DUST3R], ids=["vggt", "dust3r"])
def test_files_are_small_valid_and_say_untrained(path):
    assert path.stat().st_size < 5 * 2**20
    model = onnx.load(str(path))
    onnx.checker.check_model(model)
    assert "UNTRAINED FIXTURE" in model.doc_string
    assert model.opset_import[0].version >= 17


@pytest.mark.parametrize("s,h,w", [(1, 28, 42), (3, 56, 84), (2, 392, 518)])
def test_tiny_vggt_contract(s, h, w):
    session = ort.InferenceSession(str(TINY_VGGT), providers=["CPUExecutionProvider"])
    assert [(i.name, i.shape) for i in session.get_inputs()] == [("input_images", ["S", 3, "H", "W"])]
    x = _images(s, (s, 3, h, w))
    out = _run(TINY_VGGT, {"input_images": x})
    assert {k: v.shape for k, v in out.items()} == {
        "pose_enc": (1, s, 9),
        "depth": (1, s, h, w, 1),
        "depth_conf": (1, s, h, w),
        "world_points": (1, s, h, w, 3),
        "world_points_conf": (1, s, h, w),
        "images": (1, s, 3, h, w),
    }
    assert all(v.dtype == np.float32 and np.isfinite(v).all() for v in out.values())
    pose = out["pose_enc"][0]
    np.testing.assert_allclose(np.linalg.norm(pose[:, 3:7], axis=1), 1.0, atol=1e-5)
    assert (pose[:, 7:] > 0).all() and (pose[:, 7:] < np.pi).all()
    assert out["depth"].min() > 0 and out["depth_conf"].min() >= 1 and out["world_points_conf"].min() >= 1
    np.testing.assert_array_equal(out["images"][0], x)
    cam_from_world, K = decode_pose_enc(pose, (h, w))
    np.testing.assert_allclose(cam_from_world[0], np.eye(3, 4), atol=1e-5)  # first frame is the world
    np.testing.assert_allclose(K[:, 0, 0], K[:, 1, 1], rtol=1e-4)  # square pixels
    # Outputs depend on the pixels (not a constant graph) and per frame only on that frame's pixels
    # where the contract says so (depth), while poses are relative to the first frame.
    other = _run(TINY_VGGT, {"input_images": x[::-1].copy()})
    np.testing.assert_allclose(other["depth"][0, ::-1], out["depth"][0], rtol=1e-5)
    if s > 1:
        assert np.abs(other["pose_enc"][0, ::-1, :7] - pose[:, :7]).max() > 1e-3


@pytest.mark.parametrize("b,h,w", [(1, 32, 48), (2, 48, 64), (1, 384, 512)])
def test_tiny_dust3r_contract(b, h, w):
    session = ort.InferenceSession(str(TINY_DUST3R), providers=["CPUExecutionProvider"])
    assert [(i.name, i.shape) for i in session.get_inputs()] == [
        ("view1", ["B", 3, "H", "W"]),
        ("view2", ["B", 3, "H", "W"]),
    ]
    v1, v2 = 2 * _images(b, (b, 3, h, w)) - 1, 2 * _images(b + 10, (b, 3, h, w)) - 1
    out = _run(TINY_DUST3R, {"view1": v1, "view2": v2})
    assert {k: v.shape for k, v in out.items()} == {
        "pts3d": (b, h, w, 3),
        "conf": (b, h, w),
        "pts3d_in_other_view": (b, h, w, 3),
        "conf_in_other_view": (b, h, w),
    }
    assert all(v.dtype == np.float32 and np.isfinite(v).all() for v in out.values())
    assert out["pts3d"][..., 2].min() > 0 and out["pts3d_in_other_view"][..., 2].min() > 0
    assert out["conf"].min() >= 1 and out["conf_in_other_view"].min() >= 1
    # Points lie near pixel rays of a 60 degree camera: a least-squares focal fit is positive and close.
    pix = np.stack(np.meshgrid(np.arange(w) + 0.5 - w / 2, np.arange(h) + 0.5 - h / 2), -1).reshape(-1, 2)
    ray = (out["pts3d"][0, ..., :2] / out["pts3d"][0, ..., 2:]).reshape(-1, 2)
    focal = (pix * ray).sum() / (ray**2).sum()
    assert focal == pytest.approx(w / 2 / np.tan(np.pi / 6), rel=0.2)
    # Each view's points see both views: swapping them swaps the roles.
    swapped = _run(TINY_DUST3R, {"view1": v2, "view2": v1})
    np.testing.assert_allclose(swapped["pts3d"], out["pts3d_in_other_view"], rtol=1e-5, atol=1e-6)
    assert np.abs(out["pts3d"] - out["pts3d_in_other_view"]).max() > 1e-3


def test_outputs_are_deterministic():
    x = _images(0, (2, 3, 28, 28))
    assert all(
        np.array_equal(a, b)
        for a, b in zip(_run(TINY_VGGT, {"input_images": x}).values(), _run(TINY_VGGT, {"input_images": x}).values())
    )
    v = 2 * _images(1, (1, 3, 32, 32)) - 1
    first, second = _run(TINY_DUST3R, {"view1": v, "view2": -v}), _run(TINY_DUST3R, {"view1": v, "view2": -v})
    assert all(np.array_equal(first[k], second[k]) for k in first)


def test_regenerating_gives_identical_files_and_outputs(tmp_path):
    subprocess.run(
        [sys.executable, str(REPO / "tools" / "make_test_nets.py"), "--out", str(tmp_path)],
        check=True,
        capture_output=True,
    )
    for name, committed in (("tiny_vggt.onnx", TINY_VGGT), ("tiny_dust3r.onnx", TINY_DUST3R)):
        assert (tmp_path / name).read_bytes() == committed.read_bytes(), f"{name} differs from a fresh build"
    x = _images(2, (2, 3, 42, 56))
    fresh, old = _run(tmp_path / "tiny_vggt.onnx", {"input_images": x}), _run(TINY_VGGT, {"input_images": x})
    assert all(np.array_equal(fresh[k], old[k]) for k in old)
    # A different seed gives a different net (the seed is really used).
    subprocess.run(
        [sys.executable, str(REPO / "tools" / "make_test_nets.py"), "--out", str(tmp_path / "s1"), "--seed", "1"],
        check=True,
        capture_output=True,
    )
    assert not np.allclose(_run(tmp_path / "s1" / "tiny_vggt.onnx", {"input_images": x})["depth"], old["depth"])
