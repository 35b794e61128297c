"""Pi3 from its upstream code (tiny configuration, random weights): export, run, decode exactly.

The ONNX file is made by the user's command (``ffrecon export-model pi3 --tiny``); the reference is
upstream's own PyTorch model (rebuilt from the same seed), its own preprocessing
(``load_images_as_tensor``) and its own utilities (``se3_inverse``,
``recover_intrinsic_from_rays_d``, ``depthmap_to_absolute_camera_coordinates``).
"""

from __future__ import annotations

import importlib.util
import json
import sys
import types
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch
from PIL import Image

from ffrecon.cli import main as cli
from ffrecon.errors import ModelError
from ffrecon.models.adapters import PreprocessMode, adapter_for
from ffrecon.models.exporting import ModelExportOptions, family_module
from ffrecon.models.exporting.common import relative_difference, torch_outputs
from ffrecon.models.exporting.pi3 import closest_rotation
from ffrecon.models.exporting.upstream import import_upstream
from ffrecon.models.pi3 import ADAPTER, decode_pi3_outputs, network_size_hw, preprocess_pi3
from ffrecon.models.runner import OnnxModel
from ffrecon.types import ModelFamily, ModelInfo
from ffrecon.validate import validate_prediction

from .conftest import real_photos, upstream_dir

TOL = 1e-4
SIZE_HW = (434, 574)  # what the reference preprocessing gives 4:3 landscape photos
INFO = ModelInfo("pi3 tiny (PyTorch)", ModelFamily.PI3)


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> Path:
    """Tiny Pi3 exported by the CLI, traced with 1 frame (its own check runs 2)."""
    out = tmp_path_factory.mktemp("pi3") / "pi3_tiny.onnx"
    args = [
        "export-model",
        "pi3",
        "--upstream",
        str(upstream_dir("pi3")),
        "--tiny",
        "-o",
        str(out),
        "--height",
        str(SIZE_HW[0]),
        "--width",
        str(SIZE_HW[1]),
        "--frames",
        "1",
        "-q",
    ]
    assert cli(args) == 0
    return out


@pytest.fixture(scope="module")
def spec():
    """The same upstream model in PyTorch, rebuilt from the same seed (as export-model builds it)."""
    options = ModelExportOptions(
        family="pi3", out=Path("unused.onnx"), upstream=upstream_dir("pi3"), tiny=True, size_hw=SIZE_HW
    )
    return family_module("pi3").build(options, SIZE_HW)


@pytest.fixture(scope="module")
def upstream_utils():
    return import_upstream("pi3.utils.geometry", upstream_dir("pi3"), family="pi3")


def _upstream_cameras(outputs: dict[str, np.ndarray], geometry) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Upstream's own decoding: cam_from_world with frame 0 as world, K (pixel-index convention), depth."""
    poses = torch.from_numpy(outputs["camera_poses"][0]).double()
    cam_from_world = (geometry.se3_inverse(poses) @ poses[0]).numpy()
    K = geometry.recover_intrinsic_from_rays_d(
        torch.from_numpy(outputs["local_points"][0]).double(), force_center_principal_point=True
    ).numpy()
    return cam_from_world, K, outputs["local_points"][0, ..., 2]


def test_family_and_onnx_equals_pytorch_at_another_frame_count(exported, spec):
    model = OnnxModel(exported)
    assert model.family is ModelFamily.PI3 and adapter_for(model.family) is ADAPTER
    assert model.metadata["ffrecon.contract"] == "pi3" and "60 deg" in model.metadata["ffrecon.notes"]
    assert model.fixed_size_hw("images") == SIZE_HW
    batch, _ = preprocess_pi3(real_photos(2))  # real photos, 2 frames (traced with 1)
    want = torch_outputs(spec, (batch,))
    got = model.run({"images": batch})
    for name in spec.output_names:
        assert relative_difference(got[name], want[name]) < TOL, name


def test_svd_free_camera_head_equals_upstream_svd():
    """The exported camera head's projection onto SO(3) equals upstream's torch.svd form."""
    CameraHead = import_upstream("pi3.models.layers.camera_head", upstream_dir("pi3"), family="pi3").CameraHead
    rng = np.random.default_rng(0)
    raw = torch.from_numpy(rng.normal(size=(512, 9)).astype(np.float32))
    near = torch.linalg.qr(torch.from_numpy(rng.normal(size=(64, 3, 3))))[0].float().reshape(-1, 9) * 3 + 0.01
    for m in (raw, near):
        want = CameraHead.svd_orthogonalize(None, m)
        got = closest_rotation(m)
        assert float((got - want).abs().max()) < 1e-5
        assert torch.allclose(torch.linalg.det(got), torch.ones(len(m)), atol=1e-5)


@pytest.fixture
def fake_torchvision(monkeypatch):
    """``torchvision.transforms.ToTensor`` for upstream's loader (torchvision is not installed here).

    For RGB uint8 PIL images ToTensor is exactly ``HWC -> CHW`` and ``float / 255``. Where
    torchvision is installed, the real one is used.
    """
    if importlib.util.find_spec("torchvision") is not None:
        return
    transforms = types.ModuleType("torchvision.transforms")
    transforms.ToTensor = lambda: (
        lambda pil: torch.from_numpy(np.array(pil)).permute(2, 0, 1).contiguous().float().div(255)
    )
    package = types.ModuleType("torchvision")
    package.transforms = transforms
    monkeypatch.setitem(sys.modules, "torchvision", package)
    monkeypatch.setitem(sys.modules, "torchvision.transforms", transforms)


@pytest.mark.parametrize("orientation", ["landscape", "portrait", "mixed"])
def test_preprocessing_equals_upstream_loader(landscape_and_portrait, orientation, tmp_path, fake_torchvision):
    """Bit-identical to upstream's loader; a mixed set is resized to the first photo's size (upstream's rule)."""
    load_images_as_tensor = import_upstream("pi3.utils.basic", upstream_dir("pi3"), family="pi3").load_images_as_tensor
    mixed = [landscape_and_portrait["landscape"][0], landscape_and_portrait["portrait"][1]]
    photos = mixed if orientation == "mixed" else landscape_and_portrait[orientation]
    for k, photo in enumerate(photos):
        Image.fromarray(photo).save(tmp_path / f"{k:02d}.png")
    want = load_images_as_tensor(str(tmp_path), verbose=False).numpy()
    batch, transforms = preprocess_pi3(photos)
    assert batch.shape == want.shape and np.array_equal(batch, want)
    h, w = photos[0].shape[:2]
    assert batch.shape[2:] == network_size_hw(h, w) == (SIZE_HW[::-1] if orientation == "portrait" else SIZE_HW)
    for photo, t in zip(photos, transforms):
        assert (t.scale_x, t.scale_y) == (batch.shape[3] / photo.shape[1], batch.shape[2] / photo.shape[0])
        assert t.offset_x == t.offset_y == 0 and t.net_size_wh == batch.shape[:1:-1]
    with pytest.raises(ModelError, match="no 'pad' preprocessing"):
        preprocess_pi3(photos, PreprocessMode.PAD)


@pytest.mark.parametrize("orientation", ["landscape", "portrait"])
def test_decoded_cameras_equal_upstream_decoding(landscape_and_portrait, spec, upstream_utils, orientation):
    """640x480 / 480x640 photos: ffrecon's cam_from_world (frame 0 = world) and intrinsics in photo
    pixels equal upstream's se3_inverse and recover_intrinsic_from_rays_d on the same PyTorch outputs,
    undone by the preprocessing's per-axis resize; depth equals local z resampled at photo pixels."""
    photos = landscape_and_portrait[orientation][:2]
    batch, transforms = ADAPTER.preprocess(photos, PreprocessMode.CROP)
    outputs = torch_outputs(spec, (batch,))
    pred = decode_pi3_outputs(outputs, transforms, ["a", "b"], INFO, max_depth_side=None)
    cam_from_world, K, depth = _upstream_cameras(outputs, upstream_utils)
    np.testing.assert_allclose(pred.cam_from_world, cam_from_world[:, :3], rtol=TOL, atol=TOL)
    np.testing.assert_allclose(pred.cam_from_world[0], np.eye(4)[:3], atol=1e-6)
    (h, w), (hn, wn) = photos[0].shape[:2], batch.shape[2:]
    sx, sy = wn / w, hn / h  # computed by hand, independently of ResizeTransform
    for k in range(len(photos)):
        cam = pred.cameras[k]
        want = [
            K[k, 0, 0] / sx,
            K[k, 1, 1] / sy,
            (K[k, 0, 2] + 0.5) / sx,
            (K[k, 1, 2] + 0.5) / sy,
        ]  # index -> COLMAP centre
        np.testing.assert_allclose([cam.fx, cam.fy, cam.cx, cam.cy], want, rtol=TOL)
        assert (cam.width, cam.height) == (w, h) and (cam.cx, cam.cy) == (w / 2, h / 2)
        # Bilinear resampling at photo pixel centres ((x + 0.5) * s in network pixels), by torch's grid_sample.
        gx = 2 * (np.arange(w) + 0.5) * sx / wn - 1
        gy = 2 * (np.arange(h) + 0.5) * sy / hn - 1
        grid = torch.from_numpy(np.stack(np.meshgrid(gx, gy), -1)[None].astype(np.float32))
        sample = lambda net_map: torch.nn.functional.grid_sample(
            torch.from_numpy(net_map)[None, None], grid, align_corners=False, padding_mode="border"
        )[0, 0].numpy()  # noqa: E731
        assert relative_difference(pred.depth[k], sample(depth[k])) < TOL
        # Confidence: 1 + exp(logit) = 1 / (1 - sigmoid(logit)), the reference's sigmoid mapped to ffrecon's >= 1 scale.
        assert (
            relative_difference(
                pred.depth_conf[k],
                sample(1 / (1 - torch.sigmoid(torch.from_numpy(outputs["conf"][0, k, ..., 0])).numpy())),
            )
            < TOL
        )


@pytest.mark.parametrize("photo_hw", [SIZE_HW, SIZE_HW[::-1]], ids=["landscape", "portrait"])
def test_depth_and_points_equal_upstream_unprojection(spec, upstream_utils, photo_hw):
    """Photos at the network's size (the reference resize is then the identity): ffrecon's depth is
    local_points' z and its world points equal upstream's depthmap_to_absolute_camera_coordinates
    with the recovered intrinsics and the pose of each camera in frame 0's world.

    Upstream's unprojection puts pixel index u at coordinate u (principal point (W - 1) / 2, as its
    intrinsic recovery returns); ffrecon follows COLMAP (centre u + 0.5, principal point W / 2)."""
    h, w = photo_hw
    photos = [np.ascontiguousarray(p[:h, :w]) for p in real_photos(2, (max(h, w), max(h, w)))]
    batch, transforms = preprocess_pi3(photos)
    assert batch.shape[2:] == photo_hw and transforms[0].scale_x == transforms[0].scale_y == 1.0
    outputs = torch_outputs(spec, (batch,))
    pred = decode_pi3_outputs(outputs, transforms, ["a", "b"], INFO, max_depth_side=None)
    cam_from_world, K, depth = _upstream_cameras(outputs, upstream_utils)
    poses = outputs["camera_poses"][0].astype(np.float64)
    for k in range(2):
        np.testing.assert_array_equal(pred.depth[k], depth[k])
        world_from_cam = np.linalg.inv(poses[0]) @ poses[k]  # camera k in frame 0's world
        want, _ = upstream_utils.depthmap_to_absolute_camera_coordinates(depth[k], K[k], world_from_cam)
        assert relative_difference(pred.world_points(k), want) < TOL


def _pinhole_outputs(
    n: int, size_hw: tuple[int, int], focal: np.ndarray, seed: int = 0
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Pi3 outputs of a perfect pinhole model (centred principal point): returns (outputs, world_from_cam [n, 4, 4])."""
    rng = np.random.default_rng(seed)
    h, w = size_hw
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    z = np.stack([1.5 + 0.001 * xs + 0.002 * ys + 0.3 * k for k in range(n)])
    local = np.stack(
        [(xs - w / 2) / focal[:, None, None, 0] * z, (ys - h / 2) / focal[:, None, None, 1] * z, z], axis=-1
    )
    world_from_cam = np.tile(np.eye(4), (n, 1, 1))
    world_from_cam[:, :3, :3] = torch.linalg.qr(torch.from_numpy(rng.normal(size=(n, 3, 3))))[0].numpy()
    world_from_cam[:, :3, :3] *= np.sign(np.linalg.det(world_from_cam[:, :3, :3]))[:, None, None]
    world_from_cam[:, :3, 3] = rng.normal(size=(n, 3))
    outputs = {
        "local_points": local[None].astype(np.float32),
        "conf": np.zeros((1, n, h, w, 1), np.float32),
        "camera_poses": world_from_cam[None].astype(np.float32),
    }
    return outputs, world_from_cam


def test_decode_recovers_a_known_pinhole_camera_set():
    """Without upstream: exact local points of known cameras decode to those cameras, frame 0 as world."""
    photos = [np.zeros((480, 640, 3), np.uint8)] * 3
    batch, transforms = preprocess_pi3(photos)
    focal = np.array([[500.0, 505.0], [450.0, 452.0], [600.0, 590.0]])  # network pixels
    outputs, world_from_cam = _pinhole_outputs(3, batch.shape[2:], focal)
    pred = decode_pi3_outputs(outputs, transforms, ["a", "b", "c"], INFO)
    want = np.linalg.inv(world_from_cam) @ world_from_cam[0]
    np.testing.assert_allclose(pred.cam_from_world, want[:, :3], rtol=TOL, atol=1e-5)
    for k, t in enumerate(transforms):
        np.testing.assert_allclose(
            pred.cameras[k].K,
            [[focal[k, 0] / t.scale_x, 0, 320], [0, focal[k, 1] / t.scale_y, 240], [0, 0, 1]],
            rtol=TOL,
        )
        np.testing.assert_allclose(pred.depth_conf[k], 2.0)  # logit 0: sigmoid 0.5
    validate_prediction(pred, camera_outputs=ADAPTER.camera_outputs)


def test_bad_outputs_name_the_output():
    batch, transforms = preprocess_pi3([np.zeros((480, 640, 3), np.uint8)] * 2)
    good, _ = _pinhole_outputs(2, batch.shape[2:], np.full((2, 2), 500.0))
    with pytest.raises(ModelError, match="lack \\['camera_poses'\\]"):
        decode_pi3_outputs({k: v for k, v in good.items() if k != "camera_poses"}, transforms, ["a", "b"], INFO)
    with pytest.raises(ModelError, match="'local_points' has shape \\[2, 434, 574, 2\\]"):
        decode_pi3_outputs({**good, "local_points": good["local_points"][..., :2]}, transforms, ["a", "b"], INFO)
    bad = good["conf"].copy()
    bad[0, 1, 3, 3] = np.inf
    with pytest.raises(ModelError, match="'conf' has 1 non-finite"):
        decode_pi3_outputs({**good, "conf": bad}, transforms, ["a", "b"], INFO)


def test_untrained_rays_stop_with_the_decoded_output_error(landscape_and_portrait):
    """Left as initialised (--keep-untrained-heads), the point head's rays fit no usable focal: the
    decoded-output check names the outputs it came from instead of letting a broken camera through."""
    options = ModelExportOptions(
        family="pi3",
        out=Path("unused.onnx"),
        upstream=upstream_dir("pi3"),
        tiny=True,
        size_hw=SIZE_HW,
        keep_untrained_heads=True,
    )
    untrained = family_module("pi3").build(options, SIZE_HW)
    assert "left as initialised" in untrained.notes[0]
    batch, transforms = preprocess_pi3(landscape_and_portrait["landscape"][:2])
    pred = decode_pi3_outputs(torch_outputs(untrained, (batch,)), transforms, ["a", "b"], INFO)
    with pytest.raises(ModelError, match="'camera_poses \\(poses\\) and local_points.*unusable focal length"):
        validate_prediction(pred, camera_outputs=ADAPTER.camera_outputs)


def test_run_writes_upstream_cameras(exported, spec, upstream_utils, photo_folder, tmp_path):
    """`ffrecon run` on four 640x480 photos completes (a gate may honestly fail on untrained output)
    and feedforward/sparse holds upstream's decoded cameras, scaled to the photos."""
    out = tmp_path / "out"
    code = cli(["run", str(photo_folder), "-o", str(out), "--model", str(exported), "--no-splat", "-q"])
    assert code in (0, 5)
    report = json.loads((out / "report.json").read_text())
    assert report["verdict"]["status"] in ("ok", "gate_failed")
    rec = pycolmap.Reconstruction(out / "feedforward" / "sparse")
    files = sorted(photo_folder.glob("*.jpg"))
    batch, _ = preprocess_pi3([np.asarray(Image.open(p).convert("RGB")) for p in files])
    cam_from_world, K, _ = _upstream_cameras(torch_outputs(spec, (batch,)), upstream_utils)
    for k, path in enumerate(files):
        image = rec.find_image_with_name(path.name)
        np.testing.assert_allclose(image.cam_from_world().matrix(), cam_from_world[k, :3], rtol=TOL, atol=TOL)
        fx, fy, cx, cy = rec.cameras[image.camera_id].params
        sx, sy = SIZE_HW[1] / 640, SIZE_HW[0] / 480
        np.testing.assert_allclose([fx, fy, cx, cy], [K[k, 0, 0] / sx, K[k, 1, 1] / sy, 320, 240], rtol=TOL)
