"""Depth Anything 3: the tiny upstream model through ``export_model`` and ffrecon's adapter, checked
against upstream's own code (model forward, InputProcessor, OutputProcessor) on the same inputs.

Upstream's InputProcessor imports torchvision (absent here: it would pull another torch build) and
imageio for the import only; where they are missing, :func:`upstream_input_processor` stands in
torchvision's ``ToTensor``/``Normalize``/``CenterCrop`` with their documented arithmetic.
"""

import sys
import types
import warnings
from unittest import mock

import cv2
import numpy as np
import pytest
import torch

try:
    import depth_anything_3.model.da3  # noqa: F401
    from depth_anything_3.model import reference_view_selector as upstream_selector
    from depth_anything_3.utils.io.output_processor import OutputProcessor
except ImportError as exc:  # the package is optional (pip install --no-deps depth-anything-3==0.1.1)
    pytest.skip(f"needs the depth-anything-3 package: {exc}", allow_module_level=True)

from ffrecon.geometry.poses import compose_poses, invert_pose
from ffrecon.models import da3
from ffrecon.models.exporting import ModelExportOptions, export_model
from ffrecon.models.exporting import da3 as da3_export
from ffrecon.models.exporting.common import relative_difference, verify
from ffrecon.models.runner import OnnxModel
from ffrecon.types import ModelFamily

from .conftest import real_photos

TOLERANCE = 1e-4
SIZE_HW = (378, 504)  # 640x480 photos under DA3's processing


def _torchvision_stub() -> dict[str, types.ModuleType]:
    """``torchvision.transforms`` as upstream's InputProcessor uses it (same arithmetic as torchvision)."""

    class ToTensor:
        def __call__(self, pic):
            return (
                torch.from_numpy(np.array(pic, dtype=np.uint8)).permute(2, 0, 1).contiguous().to(torch.float32).div(255)
            )

    class Normalize:
        def __init__(self, mean, std):
            self.mean, self.std = mean, std

        def __call__(self, tensor):
            mean = torch.as_tensor(self.mean, dtype=tensor.dtype).view(-1, 1, 1)
            std = torch.as_tensor(self.std, dtype=tensor.dtype).view(-1, 1, 1)
            return tensor.sub(mean).div(std)

    class CenterCrop:
        def __init__(self, size):
            self.size = size

        def __call__(self, tensor):
            (h, w), (height, width) = self.size, tensor.shape[-2:]
            top, left = int(round((height - h) / 2.0)), int(round((width - w) / 2.0))
            return tensor[..., top : top + h, left : left + w]

    transforms = types.ModuleType("torchvision.transforms")
    transforms.ToTensor, transforms.Normalize, transforms.CenterCrop = ToTensor, Normalize, CenterCrop
    torchvision = types.ModuleType("torchvision")
    torchvision.transforms = transforms
    return {"torchvision": torchvision, "torchvision.transforms": transforms}


@pytest.fixture(scope="module")
def upstream_input_processor():
    stubs: dict[str, types.ModuleType] = {}
    for name in ("torchvision", "imageio"):
        try:
            __import__(name)
        except ImportError:
            stubs.update(_torchvision_stub() if name == "torchvision" else {"imageio": types.ModuleType("imageio")})
    with mock.patch.dict(sys.modules, stubs):
        from depth_anything_3.utils.io.input_processor import InputProcessor
    processor = InputProcessor()

    def run(images, method, intrinsics=None):
        tensor, _, K = processor(list(images), None, intrinsics, da3.PROCESS_RES, method, num_workers=1)
        return tensor, K

    return run


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """The tiny DA3 exported once with the code users run, and the same PyTorch model."""
    options = ModelExportOptions(family="da3", out=tmp_path_factory.mktemp("da3") / "da3_tiny.onnx", tiny=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # tracer warnings about the size logic the export fixes on purpose
        report = export_model(options)
    spec = da3_export.build(options, SIZE_HW)  # same seed: the same weights
    return options.out, report, spec


def _normalize(batch: np.ndarray) -> np.ndarray:
    mean = np.array(da3_export.IMAGENET_MEAN, np.float32)[:, None, None]
    std = np.array(da3_export.IMAGENET_STD, np.float32)[:, None, None]
    return (batch - mean) / std


def test_family_size_and_metadata(exported):
    path, report, _ = exported
    model = OnnxModel(path, threads=2)
    assert model.family is ModelFamily.DA3
    assert model.fixed_size_hw("images") == SIZE_HW
    assert model.metadata["ffrecon.da3.ref_view_strategy"] == "saddle_balanced"
    assert "fc_fov bias" in model.metadata["ffrecon.notes"]
    assert report.files == (path,)


def test_onnx_matches_pytorch_at_other_frame_counts(exported):
    path, report, spec = exported
    assert report.verify_count == 3 and report.worst_difference <= TOLERANCE  # export traced at 2 frames
    one = np.random.default_rng(7).uniform(0, 1, (1, 3, *SIZE_HW)).astype(np.float32)  # DA3 also works on one image
    assert max(verify(spec, path, (one,)).values()) <= TOLERANCE


@pytest.mark.parametrize("count", [1, 2, 3, 4, 6])
def test_view_selection_rewrite_equals_upstream(count):
    x = torch.randn(2, count, 5, 16, generator=torch.Generator().manual_seed(count))
    want = (
        upstream_selector.select_reference_view(x, "saddle_balanced")
        if count >= 3
        else torch.zeros(2, dtype=torch.long)
    )
    got = da3_export.select_reference_view(x, "saddle_balanced")
    assert torch.equal(got, want)
    b_idx = torch.tensor([count - 1, count // 2])
    reordered = da3_export.reorder_by_reference(x, b_idx)
    assert torch.equal(reordered, upstream_selector.reorder_by_reference(x, b_idx))
    assert torch.equal(da3_export.restore_original_order(reordered, b_idx), x)


@pytest.mark.parametrize("method", da3.METHODS)
def test_preprocessing_equals_upstream(upstream_input_processor, landscape_and_portrait, method):
    land, portrait = landscape_and_portrait["landscape"], landscape_and_portrait["portrait"]
    odd = [
        cv2.resize(land[0], (1000, 700), interpolation=cv2.INTER_AREA),
        cv2.resize(land[1], (333, 250), interpolation=cv2.INTER_AREA),
    ]
    for images in (land, portrait, odd[:1], odd[1:], [land[0], portrait[0]]):
        batch, transforms = da3.preprocess_da3(images, method)
        K_orig = np.stack(
            [
                np.array([[0.9 * w, 0, w / 2], [0, 0.9 * w, h / 2], [0, 0, 1]], np.float32)
                for h, w in (im.shape[:2] for im in images)
            ]
        )
        tensor, K_up = upstream_input_processor(images, method, K_orig)
        assert batch.shape == tuple(tensor.shape)
        np.testing.assert_allclose(_normalize(batch), tensor.numpy(), atol=1e-5)
        K_net = [
            np.diag([t.scale_x, t.scale_y, 1.0]) @ k + np.array([[0, 0, t.offset_x], [0, 0, t.offset_y], [0, 0, 0]])
            for k, t in zip(K_orig, transforms)
        ]
        np.testing.assert_allclose(np.stack(K_net), K_up.numpy(), rtol=1e-6)
        assert (
            batch.shape[2:] == da3.network_size_hw(*images[0].shape[:2], method) or len({im.shape for im in images}) > 1
        )


def _upstream_reference(net, tensor):
    """DA3's own outputs for its own preprocessed tensor: forward, then OutputProcessor (api's path)."""
    with torch.no_grad():
        raw = net(tensor[None], None, None, [], False, False, da3_export.REF_VIEW_STRATEGY)
    return raw, OutputProcessor()(raw)


def _check_against_upstream(pred, up, images, transforms, upstream_input_processor, method):
    want_pose = compose_poses(up.extrinsics.astype(np.float64), invert_pose(up.extrinsics[0].astype(np.float64))[None])
    assert relative_difference(pred.cam_from_world, want_pose) <= TOLERANCE
    np.testing.assert_allclose(pred.cam_from_world[0], np.eye(3, 4), atol=1e-6)  # float32 rotations
    # ffrecon's original-pixel intrinsics, sent through upstream's own resize bookkeeping, give DA3's.
    _, K_back = upstream_input_processor(images, method, np.stack([c.K for c in pred.cameras]).astype(np.float32))
    assert relative_difference(K_back.numpy(), up.intrinsics) <= TOLERANCE
    for k, image in enumerate(images):
        h, w = image.shape[:2]
        assert transforms[k].offset_x == transforms[k].offset_y == 0  # these sizes need no crop
        want_depth = cv2.resize(up.depth[k], (w, h), interpolation=cv2.INTER_LINEAR)
        assert relative_difference(pred.depth[k], want_depth) <= TOLERANCE
        assert (
            relative_difference(pred.depth_conf[k], cv2.resize(up.conf[k], (w, h), interpolation=cv2.INTER_LINEAR))
            <= TOLERANCE
        )
        assert (pred.depth_conf[k] >= 1).all()


@pytest.mark.parametrize("orientation", ["landscape", "portrait"])
@pytest.mark.parametrize("mode", da3.ADAPTER.modes, ids=lambda m: m.value)
def test_decode_equals_upstream(exported, upstream_input_processor, landscape_and_portrait, orientation, mode):
    path, _, spec = exported
    images = landscape_and_portrait[orientation]
    names = [f"{k}.jpg" for k in range(len(images))]
    method = da3.MODE_METHODS[mode]
    batch, transforms = da3.ADAPTER.preprocess(images, mode)
    tensor, _ = upstream_input_processor(images, method)
    raw, up = _upstream_reference(spec.module.net, tensor)
    model = OnnxModel(path, threads=2)
    # Decoding alone: the same PyTorch outputs through ffrecon's decode and upstream's OutputProcessor.
    outputs = {k: raw[k].numpy() for k in da3.OUTPUT_NAMES}
    pred = da3.ADAPTER.decode(outputs, transforms, names, model.info(), None)
    _check_against_upstream(pred, up, images, transforms, upstream_input_processor, method)
    if batch.shape[2:] == SIZE_HW:  # end to end through the ONNX file exported for this size
        pred = da3.ADAPTER.decode(model.run({"images": batch}), transforms, names, model.info(), None)
        _check_against_upstream(pred, up, images, transforms, upstream_input_processor, method)


def test_one_image(exported):
    path, _, _ = exported
    model = OnnxModel(path, threads=2)
    image = real_photos(1)[0]
    batch, transforms = da3.ADAPTER.preprocess([image], da3.ADAPTER.modes[0])
    pred = da3.ADAPTER.decode(model.run({"images": batch}), transforms, ["0.jpg"], model.info(), 512)
    np.testing.assert_allclose(pred.cam_from_world[0], np.eye(3, 4), atol=1e-6)  # float32 rotations
    cam = pred.cameras[0]
    assert (cam.width, cam.height) == (640, 480) and 20 < cam.fov_deg()[0] < 120
    assert max(pred.depth[0].shape) == 512 and pred.valid_mask(0).all()


def test_decode_rejects_bad_outputs(exported):
    path, _, _ = exported
    info = OnnxModel(path, threads=2).info()
    batch, transforms = da3.preprocess_da3(real_photos(2))
    good = {
        "depth": np.ones((1, 2, *SIZE_HW), np.float32),
        "depth_conf": np.full((1, 2, *SIZE_HW), 2, np.float32),
        "extrinsics": np.tile(np.eye(3, 4, dtype=np.float32), (1, 2, 1, 1)),
        "intrinsics": np.tile(np.diag([400.0, 400, 1]).astype(np.float32), (1, 2, 1, 1)),
    }
    da3.decode_da3_outputs(good, transforms, ["a", "b"], info)
    from ffrecon.errors import ModelError

    for key, bad in (
        ("depth", np.ones((1, 3, *SIZE_HW), np.float32)),
        ("extrinsics", np.full((1, 2, 3, 4), np.nan, np.float32)),
        ("intrinsics", np.zeros((1, 2, 3, 3), np.float32)),
    ):
        with pytest.raises(ModelError, match=key):
            da3.decode_da3_outputs({**good, key: bad}, transforms, ["a", "b"], info)


def test_cli_run_writes_upstream_cameras(exported, upstream_input_processor, photo_folder, tmp_path):
    """`ffrecon run` on four 640x480 photos completes (a gate may honestly fail on untrained output)
    and feedforward/sparse holds DA3's own poses (relative to the first photo) and intrinsics."""
    import pycolmap
    from PIL import Image

    from ffrecon.cli import main

    path, _, spec = exported
    out = tmp_path / "out"
    code = main(["run", str(photo_folder), "-o", str(out), "--model", str(path), "--no-splat", "-q"])
    assert code in (0, 5)  # 5: an honest gate failure on untrained output
    rec = pycolmap.Reconstruction(out / "feedforward" / "sparse")
    files = sorted(photo_folder.glob("*.jpg"))
    images = [np.asarray(Image.open(f).convert("RGB")) for f in files]
    method = da3.MODE_METHODS[da3.ADAPTER.modes[0]]
    tensor, _ = upstream_input_processor(images, method)
    _, up = _upstream_reference(spec.module.net, tensor)
    want_pose = compose_poses(up.extrinsics.astype(np.float64), invert_pose(up.extrinsics[0].astype(np.float64))[None])
    sx, sy = SIZE_HW[1] / 640, SIZE_HW[0] / 480
    for k, f in enumerate(files):
        image = rec.find_image_with_name(f.name)
        assert relative_difference(image.cam_from_world().matrix(), want_pose[k]) <= TOLERANCE
        fx, fy, cx, cy = rec.cameras[image.camera_id].params
        K = up.intrinsics[k].astype(np.float64)
        np.testing.assert_allclose(
            [fx, fy, cx, cy], [K[0, 0] / sx, K[1, 1] / sy, K[0, 2] / sx, K[1, 2] / sy], rtol=TOLERANCE
        )
