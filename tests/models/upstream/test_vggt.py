"""VGGT from its upstream code (tiny configuration, random weights): export, run, decode exactly.

The ONNX file is made by the user's command (``ffrecon export-model``); the reference is upstream's
own PyTorch model (rebuilt from the same seed) and its own decoding utilities
(``pose_encoding_to_extri_intri``, ``unproject_depth_map_to_point_map``).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch

from ffrecon.cli import main as cli
from ffrecon.models.adapters import PreprocessMode
from ffrecon.models.exporting import ModelExportOptions, family_module
from ffrecon.models.exporting.common import relative_difference, torch_outputs
from ffrecon.models.runner import OnnxModel
from ffrecon.models.vggt import decode_vggt_outputs, network_size_hw, preprocess_vggt
from ffrecon.types import ModelFamily

from .conftest import real_photos, upstream_dir

TOL = 1e-4


def _export(tmp: Path, size_hw: tuple[int, int], *extra: str) -> Path:
    out = tmp / f"vggt_{size_hw[1]}x{size_hw[0]}{'_'.join(extra)}.onnx"
    args = [
        "export-model",
        "vggt",
        "--upstream",
        str(upstream_dir("vggt")),
        "--tiny",
        "-o",
        str(out),
        "--height",
        str(size_hw[0]),
        "--width",
        str(size_hw[1]),
        "-q",
        *extra,
    ]
    assert cli(args) == 0
    return out


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """Tiny VGGT exported by the CLI at the two sizes 4:3 photos need (crop 518x392; portrait/pad 518x518)."""
    tmp = tmp_path_factory.mktemp("vggt")
    return {size: _export(tmp, size) for size in ((392, 518), (518, 518))}


@pytest.fixture(scope="module")
def torch_spec():
    """The same upstream model in PyTorch, rebuilt from the same seed (as export-model builds it)."""

    def build(size_hw):
        options = ModelExportOptions(
            family="vggt", out=Path("unused.onnx"), upstream=upstream_dir("vggt"), tiny=True, size_hw=size_hw
        )
        return family_module("vggt").build(options, size_hw)

    torch.manual_seed(0)
    return build


def _upstream_decode(pose_enc: np.ndarray, size_hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    from vggt.utils.pose_enc import pose_encoding_to_extri_intri

    extri, intri = pose_encoding_to_extri_intri(torch.from_numpy(pose_enc), size_hw)
    return extri[0].double().numpy(), intri[0].double().numpy()


def test_family_and_onnx_equals_pytorch_at_another_frame_count(exported, torch_spec):
    path = exported[(392, 518)]
    model = OnnxModel(path)
    assert model.family is ModelFamily.MULTIVIEW
    assert model.metadata["ffrecon.contract"] == "multiview" and "60.0 deg" in model.metadata["ffrecon.notes"]
    spec = torch_spec((392, 518))
    inputs = spec.make_inputs(5, np.random.default_rng(3))  # traced with 2 frames
    want = torch_outputs(spec, inputs)
    got = model.run({"input_images": inputs[0]})
    for name in spec.output_names:
        assert relative_difference(got[name], want[name]) < TOL, name


def test_fused_attention_export_equals_pytorch_and_the_math_export(exported, torch_spec, tmp_path):
    """``--fused-attention`` writes every attention as onnxruntime's MultiHeadAttention (no Softmax left)
    and computes what PyTorch and the MatMul-Softmax-MatMul export compute (CPU provider here; the CUDA
    provider's kernels were checked on an H100, docs/benchmarks.md)."""
    import onnx

    path = _export(tmp_path, (392, 518), "--fused-attention")
    graph = onnx.load(str(path)).graph
    ops = [n.op_type for n in graph.node]
    assert "Softmax" not in ops and ops.count("MultiHeadAttention") >= 8  # 4 frame + 4 global layers, camera trunk
    model = OnnxModel(path)
    assert model.metadata["ffrecon.attention"] == "fused"
    assert OnnxModel(exported[(392, 518)]).metadata["ffrecon.attention"] == "math"
    spec = torch_spec((392, 518))
    inputs = spec.make_inputs(4, np.random.default_rng(5))
    want = torch_outputs(spec, inputs)
    got = model.run({"input_images": inputs[0]})
    math = OnnxModel(exported[(392, 518)]).run({"input_images": inputs[0]})
    for name in spec.output_names:
        assert relative_difference(got[name], want[name]) < TOL, name
        assert relative_difference(got[name], math[name]) < TOL, name


@pytest.mark.parametrize("orientation", ["landscape", "portrait"])
@pytest.mark.parametrize("mode", [PreprocessMode.CROP, PreprocessMode.PAD])
def test_decoded_cameras_equal_upstream_decoding(exported, torch_spec, orientation, mode):
    """640x480 / 480x640 photos: cam_from_world and intrinsics in photo pixels equal upstream's
    pose_encoding_to_extri_intri, scaled by the preprocessing's resize and crop/pad offsets."""
    size = (640, 480) if orientation == "landscape" else (480, 640)
    photos = real_photos(3, size)
    batch, transforms = preprocess_vggt(photos, mode)
    size_hw = tuple(batch.shape[2:])
    assert size_hw == network_size_hw(size[1], size[0], mode)
    outputs = OnnxModel(exported[size_hw]).run({"input_images": batch})
    pred = decode_vggt_outputs(outputs, transforms, ["a", "b", "c"], OnnxModel(exported[size_hw]).info())
    extri, intri = _upstream_decode(outputs["pose_enc"], size_hw)
    np.testing.assert_allclose(pred.cam_from_world, extri, rtol=TOL, atol=TOL)
    w, h = size
    for k, t in enumerate(transforms):
        # Undo the resize (scale) and the crop or pad (offset) by hand, independently of ResizeTransform.
        s = 518 / max(w, h) if mode is PreprocessMode.PAD else 518 / w
        new_h = round(h * s / 14) * 14
        off_y = (518 - new_h) // 2 if mode is PreprocessMode.PAD else -((new_h - 518) // 2 if new_h > 518 else 0)
        new_w = round(w * s / 14) * 14 if mode is PreprocessMode.PAD else 518
        off_x = (518 - new_w) // 2 if mode is PreprocessMode.PAD else 0
        sx, sy = new_w / w, new_h / h
        K = intri[k]
        want = np.array([K[0, 0] / sx, K[1, 1] / sy, (K[0, 2] - off_x) / sx, (K[1, 2] - off_y) / sy])
        cam = pred.cameras[k]
        np.testing.assert_allclose([cam.fx, cam.fy, cam.cx, cam.cy], want, rtol=TOL)
        assert (cam.width, cam.height) == size


@pytest.mark.parametrize(
    "photo_hw,mode",
    [
        ((392, 518), PreprocessMode.CROP),
        ((686, 518), PreprocessMode.CROP),
        ((518, 392), PreprocessMode.PAD),
        ((392, 518), PreprocessMode.PAD),
    ],
)
def test_depth_and_points_equal_upstream_unprojection(exported, photo_hw, mode):
    """Photos at the network's scale (crop and pad only): ffrecon's depth in photo pixels equals the
    network's depth, and its world points equal upstream's unproject_depth_map_to_point_map.

    Upstream's unprojection puts pixel index u at coordinate u (principal point at index W/2);
    ffrecon follows COLMAP (pixel u's centre at u + 0.5, principal point at the image centre W/2).
    Upstream's own intrinsics shifted by half a pixel give upstream's utility the same rays."""
    from vggt.utils.geometry import unproject_depth_map_to_point_map

    h, w = photo_hw
    photos = [np.ascontiguousarray(p[:h, :w]) for p in real_photos(2, (max(w, 518), max(h, 518)))]
    batch, transforms = preprocess_vggt(photos, mode)
    size_hw = tuple(batch.shape[2:])
    outputs = OnnxModel(exported[size_hw]).run({"input_images": batch})
    pred = decode_vggt_outputs(
        outputs, transforms, ["a", "b"], OnnxModel(exported[size_hw]).info(), max_depth_side=None
    )
    extri, intri = _upstream_decode(outputs["pose_enc"], size_hw)
    net_depth = outputs["depth"][0, ..., 0]
    intri_index = intri.copy()
    intri_index[:, :2, 2] -= 0.5  # COLMAP-rule principal point -> upstream's integer-centre convention
    up_points = unproject_depth_map_to_point_map(net_depth[..., None], extri, intri_index)
    for k, t in enumerate(transforms):
        # network pixel (r, c) is photo pixel (r - off_y, c - off_x) at scale 1
        oy, ox = int(t.offset_y), int(t.offset_x)
        assert t.scale_x == t.scale_y == 1.0
        rows = slice(max(0, oy), max(0, oy) + min(h, size_hw[0]))
        cols = slice(max(0, ox), max(0, ox) + min(w, size_hw[1]))
        photo_rows = slice(max(0, -oy), max(0, -oy) + min(h, size_hw[0]))
        photo_cols = slice(max(0, -ox), max(0, -ox) + min(w, size_hw[1]))
        np.testing.assert_allclose(pred.depth[k][photo_rows, photo_cols], net_depth[k][rows, cols], rtol=TOL)
        pts = pred.world_points(k)[photo_rows, photo_cols]
        want = up_points[k][rows, cols]
        assert relative_difference(pts, want) < TOL
        if h > size_hw[0]:  # rows cropped away have no depth
            assert (pred.depth[k][: max(0, -oy)] == 0).all()


def test_run_writes_cameras_equal_to_upstream(exported, torch_spec, photo_folder, tmp_path):
    """`ffrecon run` on 640x480 photos: feedforward/sparse holds upstream's decoded cameras, scaled to the photos."""
    from vggt.utils.pose_enc import pose_encoding_to_extri_intri

    out = tmp_path / "out"
    code = cli(["run", str(photo_folder), "-o", str(out), "--model", str(exported[(392, 518)]), "--no-splat", "-q"])
    assert code in (0, 5)  # untrained output: a gate may honestly fail; never a crash
    report = json.loads((out / "report.json").read_text())
    assert report["verdict"]["status"] in ("ok", "gate_failed")
    rec = pycolmap.Reconstruction(out / "feedforward" / "sparse")
    photos = [
        np.asarray(__import__("PIL.Image", fromlist=["Image"]).open(p).convert("RGB"))
        for p in sorted(photo_folder.glob("*.jpg"))
    ]
    batch, _ = preprocess_vggt(photos, PreprocessMode.CROP)
    spec = torch_spec((392, 518))
    pose_enc = torch_outputs(spec, (batch,))["pose_enc"]
    extri, intri = pose_encoding_to_extri_intri(torch.from_numpy(pose_enc), (392, 518))
    scale = 518 / 640
    for k, path in enumerate(sorted(photo_folder.glob("*.jpg"))):
        image = rec.find_image_with_name(path.name)
        np.testing.assert_allclose(image.cam_from_world().matrix(), extri[0, k].double().numpy(), rtol=TOL, atol=TOL)
        fx, fy, cx, cy = rec.cameras[image.camera_id].params
        K = intri[0, k].double().numpy()
        np.testing.assert_allclose(
            [fx, fy, cx, cy], [K[0, 0] / scale, K[1, 1] * 480 / 392, K[0, 2] / scale, K[1, 2] * 480 / 392], rtol=TOL
        )


def test_untrained_fov_stops_within_a_minute_with_exit_3(tmp_path, photo_folder):
    """The same tiny VGGT with its field-of-view bias left at random: the decoded focal length is infinite."""
    model = _export(tmp_path, (392, 518), "--keep-untrained-heads")
    out = tmp_path / "out"
    (out / ".ffrecon").mkdir(parents=True)  # an earlier ffrecon output (its marker)
    (out / "earlier").mkdir(parents=True)
    (out / "earlier" / "result.txt").write_text("keep me")
    start = time.monotonic()
    code = cli(["run", str(photo_folder), "-o", str(out), "--model", str(model), "--overwrite", "-q"])
    assert code == 3
    assert time.monotonic() - start < 60
    assert (out / "earlier" / "result.txt").read_text() == "keep me"
    assert not (out / "report.json").exists()


def _to_tensor_stub():
    """torchvision.transforms.ToTensor as upstream's loader uses it (torchvision has no CPU wheel here)."""
    import sys
    import types

    class ToTensor:
        def __call__(self, pic):
            return torch.from_numpy(np.array(pic, dtype=np.uint8)).permute(2, 0, 1).contiguous().float().div(255)

    transforms = types.ModuleType("torchvision.transforms")
    transforms.ToTensor = ToTensor
    torchvision = types.ModuleType("torchvision")
    torchvision.transforms = transforms
    return (
        {"torchvision": torchvision, "torchvision.transforms": transforms} if "torchvision" not in sys.modules else {}
    )


@pytest.mark.parametrize("size", [(640, 480), (480, 640), (500, 500)], ids=["landscape", "portrait", "square"])
@pytest.mark.parametrize("mode", [PreprocessMode.CROP, PreprocessMode.PAD], ids=lambda m: m.value)
def test_preprocessing_equals_upstream_loader(exported, tmp_path, size, mode):
    """ffrecon's VGGT preprocessing gives the same tensor as upstream's load_and_preprocess_images."""
    import sys
    from unittest import mock

    from PIL import Image

    photos = real_photos(2, size)
    paths = []
    for k, photo in enumerate(photos):
        paths.append(tmp_path / f"{k}.png")
        Image.fromarray(photo).save(paths[-1])
    with mock.patch.dict(sys.modules, _to_tensor_stub()):
        sys.modules.pop("vggt.utils.load_fn", None)
        from vggt.utils.load_fn import load_and_preprocess_images

        want = load_and_preprocess_images([str(p) for p in paths], mode=mode.value).numpy()
        sys.modules.pop("vggt.utils.load_fn", None)
    got, _ = preprocess_vggt(photos, mode)
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, atol=1e-6)
