"""Decoded-output checks: degenerate cameras, poses and depth stop the run with a clear ModelError."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ffrecon.errors import ModelError, NonFiniteError
from ffrecon.geometry.alignment import umeyama
from ffrecon.types import ModelFamily, ModelInfo, PinholeCamera, Prediction
from ffrecon.validate import validate_prediction


def _prediction(n: int = 3) -> Prediction:
    cams = tuple(PinholeCamera(64, 48, 55.0, 55.0, 32.0, 24.0) for _ in range(n))
    poses = np.tile(np.eye(3, 4), (n, 1, 1))
    poses[:, 0, 3] = np.arange(n)
    depth = tuple(np.full((48, 64), 2.0, np.float32) for _ in range(n))
    conf = tuple(np.full((48, 64), 3.0, np.float32) for _ in range(n))
    return Prediction(
        tuple(f"f{k}.jpg" for k in range(n)), poses, cams, depth, conf, ModelInfo("m.onnx", ModelFamily.MULTIVIEW)
    )


def test_plausible_prediction_passes():
    validate_prediction(_prediction())


@pytest.mark.parametrize("fx", [np.inf, 0.0, -5.0, np.nan, 1e6])
def test_unusable_focal_names_output_and_frames(fx):
    pred = _prediction()
    cams = (dataclasses.replace(pred.cameras[0], fx=fx),) + pred.cameras[1:]
    with pytest.raises(ModelError) as err:
        validate_prediction(dataclasses.replace(pred, cameras=cams), camera_outputs="pose_enc")
    text = str(err.value)
    assert "pose_enc" in text and "focal length" in text and "1 of 3 frames: f0.jpg" in text


def test_non_rigid_pose_rejected():
    pred = _prediction()
    poses = pred.cam_from_world.copy()
    poses[1, :3, :3] *= 2.0  # a non-unit quaternion decoded without normalising
    with pytest.raises(ModelError, match="invalid poses.*f1.jpg.*not orthonormal"):
        validate_prediction(dataclasses.replace(pred, cam_from_world=poses))


@pytest.mark.parametrize(
    "case,message",
    [
        ("zero", "zero or negative everywhere"),
        ("negconf", "confidence down to"),
        ("inf", "points at infinity"),
        ("nan", "NaN"),
    ],
)
def test_unusable_depth_rejected(case, message):
    pred = _prediction()
    depth, conf = list(pred.depth), list(pred.depth_conf)
    if case == "zero":
        depth[2] = np.zeros_like(depth[2])
    elif case == "negconf":
        conf[2] = conf[2] - 10.0
    elif case == "inf":
        depth[2] = depth[2].copy()
        depth[2][0, 0] = 1e9
    else:
        depth[2] = np.full_like(depth[2], np.nan)
    with pytest.raises(ModelError, match=message):
        validate_prediction(dataclasses.replace(pred, depth=tuple(depth), depth_conf=tuple(conf)))


def test_iterative_steps_refuse_nan_inputs():
    """A NaN that slipped through must not reach LAPACK (where it can spin forever)."""
    src = np.random.default_rng(0).normal(size=(10, 3))
    dst = src.copy()
    dst[3, 1] = np.nan
    with pytest.raises(NonFiniteError, match="non-finite"):
        umeyama(src, dst)


def test_refinement_refuses_infinite_focal_before_any_work(tmp_path):
    from ffrecon.sfm.refine.options import RefineInputs, RefineOptions
    from ffrecon.sfm.refine.run import run_refine

    pred = _prediction()
    for name in pred.names:
        (tmp_path / name).write_bytes(b"")  # never read: the check comes first
    cams = tuple(dataclasses.replace(c, fx=np.inf) for c in pred.cameras)
    with pytest.raises(ModelError, match="focal length"):
        run_refine(RefineInputs(tmp_path), dataclasses.replace(pred, cameras=cams), RefineOptions(), tmp_path / "out")
