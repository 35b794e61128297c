"""Monocular depth: a tiny ``transformers`` Depth Anything through ``export_model`` and ffrecon's
adapter, checked against ``transformers``' own image processor, model and post-processing."""

import warnings

import cv2
import numpy as np
import pytest
import torch

from ffrecon.errors import InputError
from ffrecon.geometry.projection import pixel_centers, project_points
from ffrecon.models import monodepth
from ffrecon.models.exporting import ModelExportOptions, export_model
from ffrecon.models.exporting import monodepth as mono_export
from ffrecon.models.exporting.common import relative_difference, verify
from ffrecon.models.runner import OnnxModel
from ffrecon.types import ModelFamily

from .conftest import real_photos

transformers = pytest.importorskip(
    "transformers", reason="needs transformers (Depth Anything's reference implementation)"
)
if not hasattr(transformers, "DepthAnythingForDepthEstimation") or not hasattr(transformers, "DPTImageProcessorPil"):
    pytest.skip(
        "needs transformers >= 5 (DepthAnythingForDepthEstimation, DPTImageProcessorPil)", allow_module_level=True
    )

TOLERANCE = 1e-4
SIZES = {"landscape": (518, 686), "portrait": (686, 518)}  # 640x480 and 480x640 photos


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """The tiny model exported (with the code users run) at both photo orientations, and its PyTorch twin."""
    folder = tmp_path_factory.mktemp("monodepth")
    models = {}
    for orientation, size_hw in SIZES.items():
        # The portrait file is not re-verified here: the landscape export's verification covers the graph.
        options = ModelExportOptions(
            family="monodepth",
            out=folder / f"{orientation}.onnx",
            tiny=True,
            size_hw=size_hw,
            verify=orientation == "landscape",
        )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            report = export_model(options)
        models[orientation] = (options.out, report, mono_export.build(options, size_hw))  # same seed: same weights
    return models


@pytest.fixture(scope="module")
def processor():
    """Depth Anything V2's preprocessor_config.json settings, PIL backend."""
    return transformers.DPTImageProcessorPil(
        do_resize=True,
        size={"height": 518, "width": 518},
        keep_aspect_ratio=True,
        ensure_multiple_of=14,
        resample=3,
        do_rescale=True,
        do_normalize=True,
        image_mean=list(mono_export.IMAGENET_MEAN),
        image_std=list(mono_export.IMAGENET_STD),
        do_pad=False,
    )


def _normalize(batch: np.ndarray) -> np.ndarray:
    mean = np.array(mono_export.IMAGENET_MEAN, np.float32)[:, None, None]
    std = np.array(mono_export.IMAGENET_STD, np.float32)[:, None, None]
    return (batch - mean) / std


def test_family_and_metadata(exported):
    path, report, _ = exported["landscape"]
    model = OnnxModel(path, threads=2)
    assert model.family is ModelFamily.MONODEPTH
    assert model.fixed_size_hw("pixel_values") == SIZES["landscape"]
    assert model.metadata["ffrecon.depth_kind"] == "relative_inverse"
    assert model.info().metadata["ffrecon.depth_kind"] == "relative_inverse"


def test_onnx_matches_pytorch_at_other_batch(exported):
    path, report, spec = exported["landscape"]
    assert report.verify_count == 3 and report.worst_difference <= TOLERANCE  # traced at a batch of 2
    x = np.random.default_rng(3).uniform(0, 1, (1, 3, *SIZES["landscape"])).astype(np.float32)
    assert max(verify(spec, path, (x,)).values()) <= TOLERANCE


def test_preprocessing_equals_transformers(processor, landscape_and_portrait):
    land = landscape_and_portrait["landscape"]
    odd = [
        cv2.resize(land[0], (1000, 700), interpolation=cv2.INTER_AREA),
        cv2.resize(land[1], (333, 250), interpolation=cv2.INTER_AREA),
    ]
    for images in (land, landscape_and_portrait["portrait"], odd[:1], odd[1:]):
        batch, transforms = monodepth.preprocess_monodepth(images)
        want = processor(images=list(images), return_tensors="pt")["pixel_values"].numpy()
        assert batch.shape == want.shape
        np.testing.assert_allclose(_normalize(batch), want, atol=1e-5)
        h, w = images[0].shape[:2]
        assert batch.shape[2:] == monodepth.network_size_hw(h, w) == mono_export.size_for_photo(h, w)
        assert transforms[0].scale_x == batch.shape[3] / w and transforms[0].scale_y == batch.shape[2] / h


def _reference_inverse_depth(spec, processor, image):
    """transformers' own path: processor, model, post_process_depth_estimation to the photo's size."""
    pixel_values = processor(images=[image], return_tensors="pt")["pixel_values"]
    with torch.no_grad():
        outputs = spec.module.model(pixel_values=pixel_values)
    return processor.post_process_depth_estimation(outputs, target_sizes=[image.shape[:2]])[0][
        "predicted_depth"
    ].numpy()


@pytest.mark.parametrize("orientation", ["landscape", "portrait"])
def test_decode_equals_transformers_post_processing(exported, processor, landscape_and_portrait, orientation):
    path, _, spec = exported[orientation]
    model = OnnxModel(path, threads=2)
    image = landscape_and_portrait[orientation][0]
    reference = _reference_inverse_depth(spec, processor, image)
    batch, transforms = monodepth.ADAPTER.preprocess([image], monodepth.ADAPTER.modes[0])
    outputs = model.run({"pixel_values": batch})
    # The interpolation itself: decoded as "metric" the values are passed through (negatives -> 0).
    as_is = monodepth.decode_monodepth(outputs, transforms, ["a.jpg"], model.info(), depth_kind="metric")
    assert as_is.depth[0].shape == image.shape[:2]
    assert relative_difference(as_is.depth[0], np.maximum(reference, 0)) <= TOLERANCE
    # Relative inverse depth (the model's metadata) under the stated assumption: median(d) / d.
    pred = monodepth.ADAPTER.decode(outputs, transforms, ["a.jpg"], model.info(), None)
    valid = reference > monodepth.MIN_INVERSE_FRACTION * np.median(reference[reference > 0])
    median = np.median(reference[valid])
    agree = (pred.depth[0] > 0) == valid  # pixels at the 1/1000 cut may fall either side
    assert agree.mean() > 0.9999
    both = agree & valid
    # Compared in the model's (inverse) space, where a 1e-4 tolerance means the same everywhere.
    assert relative_difference(median / pred.depth[0][both], reference[both]) <= TOLERANCE
    assert abs(np.median(pred.depth[0][pred.depth[0] > 0]) - 1) < 1e-2
    np.testing.assert_array_equal(pred.depth_conf[0], (pred.depth[0] > 0).astype(np.float32))


@pytest.mark.parametrize("focal_px", [None, 800.0])
def test_one_photo_point_cloud_reprojects_to_its_pixels(exported, focal_px):
    path, _, _ = exported["landscape"]
    model = OnnxModel(path, threads=2)
    image = real_photos(1)[0]
    pred = monodepth.predict_monodepth(
        image, "0.jpg", lambda b: model.run({"pixel_values": b}), model.info(), focal_px=focal_px
    )
    cam = pred.cameras[0]
    assert (cam.width, cam.height, cam.cx, cam.cy) == (640, 480, 320.0, 240.0)
    assert cam.fx == cam.fy == pytest.approx(focal_px or 320 / np.tan(np.radians(30)))
    np.testing.assert_array_equal(pred.cam_from_world[0], np.eye(3, 4))
    valid = pred.valid_mask(0)
    assert valid.mean() > 0.5
    points = pred.world_points(0)[valid]
    uv, z = project_points(points, cam.K, pred.cam_from_world[0])
    np.testing.assert_allclose(uv, pixel_centers(480, 640)[valid], atol=1e-6)
    np.testing.assert_allclose(z, pred.depth[0][valid], rtol=1e-6)


def test_one_photo_only(exported):
    path, _, _ = exported["landscape"]
    info = OnnxModel(path, threads=2).info()
    batch, transforms = monodepth.preprocess_monodepth(real_photos(2))
    with pytest.raises(InputError, match="one photo"):
        monodepth.decode_monodepth(
            {"predicted_depth": np.ones((2, *batch.shape[2:]), np.float32)}, transforms, ["a", "b"], info
        )


def test_cli_run_one_photo(exported, tmp_path):
    from PIL import Image

    from ffrecon.cli import main

    path, _, _ = exported["landscape"]
    folder = tmp_path / "photo"
    folder.mkdir()
    Image.fromarray(real_photos(1)[0]).save(folder / "0.jpg", quality=95)
    out = tmp_path / "out"
    assert main(["run", str(folder), "-o", str(out), "--model", str(path), "--no-splat", "-q"]) == 0
    assert (out / "feedforward" / "sparse").is_dir() and (out / "points.ply").is_file()


def test_export_from_downloaded_metric_folder(tmp_path):
    """A Hugging Face folder (config.json, model.safetensors, preprocessor_config.json), as users download it."""
    import json

    folder = tmp_path / "Depth-Anything-V2-Metric-tiny"
    torch.manual_seed(0)
    transformers.DepthAnythingForDepthEstimation(mono_export.config_for("tiny", metric=True)).save_pretrained(folder)
    (folder / "preprocessor_config.json").write_text(
        json.dumps(
            {
                "image_processor_type": "DPTImageProcessor",
                "size": {"height": 518, "width": 518},
                "keep_aspect_ratio": True,
                "ensure_multiple_of": 14,
                "resample": 3,
                "image_mean": [0.5, 0.5, 0.5],
                "image_std": [0.25, 0.25, 0.25],
            }
        )
    )
    out = tmp_path / "metric.onnx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        export_model(
            ModelExportOptions(family="monodepth", out=out, checkpoint=str(folder), size_hw=(126, 168), verify=False)
        )
    model = OnnxModel(out, threads=2)
    assert (
        model.metadata["ffrecon.depth_kind"] == "metric"
        and float(model.metadata["ffrecon.max_depth"]) == mono_export.METRIC_MAX_DEPTH
    )
    assert "0.25" in model.metadata["ffrecon.notes"]  # the folder's normalisation, not ImageNet's
    x = np.random.default_rng(0).uniform(0, 1, (1, 3, 126, 168)).astype(np.float32)
    reference = transformers.DepthAnythingForDepthEstimation.from_pretrained(folder).eval()
    with torch.no_grad():
        want = reference(pixel_values=(torch.from_numpy(x) - 0.5) / 0.25).predicted_depth.numpy()
    assert relative_difference(model.run({"pixel_values": x})["predicted_depth"], want) <= TOLERANCE


def test_processor_settings_from_metadata():
    """A DPT-style export records its own processor settings; ffrecon's preprocessing follows them."""
    import json

    from ffrecon.types import ModelInfo

    info = ModelInfo(
        "dpt.onnx",
        ModelFamily.MONODEPTH,
        metadata={
            "ffrecon.monodepth.processor": json.dumps(
                {
                    "size": {"height": 384, "width": 384},
                    "keep_aspect_ratio": False,
                    "ensure_multiple_of": 32,
                    "resample": 2,
                }
            )
        },
    )
    settings = monodepth.ProcessorSettings.from_model(info)
    assert settings == monodepth.ProcessorSettings((384, 384), False, 32, 2)
    batch, transforms = monodepth.preprocess_monodepth(real_photos(1), settings=settings)
    assert batch.shape == (1, 3, 384, 384) and transforms[0].scale_x == 384 / 640
    assert (
        monodepth.ProcessorSettings.from_model(ModelInfo("x", ModelFamily.MONODEPTH)) == monodepth.ProcessorSettings()
    )
