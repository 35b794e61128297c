"""MapAnything contract: an ONNX stand-in with known cameras and depth decodes back to them exactly.

MapAnything itself cannot be built offline (its encoder loads DINOv2 through torch.hub), so the
model here is a small torch module, exported with the TorchScript exporter, whose outputs are what
a perfect MapAnything would return for a known synthetic camera set: unit rays through the network
pixels of known intrinsics, distances along them from a known planar z-depth, world_from_cam poses
as translation + xyzw quaternion (metric-scaled like upstream's), and ``1 + exp`` confidences.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from ffrecon.errors import ModelError
from ffrecon.geometry.poses import compose_poses, invert_pose
from ffrecon.geometry.rotations import matrix_to_quat_xyzw, random_rotation
from ffrecon.models.adapters import PreprocessMode, adapter_for
from ffrecon.models.mapanything import ADAPTER, decode_mapanything_outputs, network_size_hw, preprocess_mapanything
from ffrecon.models.multiview import predict_multiview
from ffrecon.models.runner import OnnxModel
from ffrecon.types import ModelFamily, ModelInfo

TOL = 1e-4
VIEWS = 3  # the stand-in is exported with 2 views and run with 3
METRIC_SCALE = 3.7  # applied to translations and distances, as upstream's scale head does


def _truth(width: int, height: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Known cam_from_world [V, 3, 4] (arbitrary world) and K [V, 3, 3] in original photo pixels."""
    rng = np.random.default_rng(seed)
    cam_from_world = np.concatenate([random_rotation(rng, VIEWS), rng.normal(size=(VIEWS, 3, 1))], axis=2)
    f = rng.uniform(0.7, 1.3, VIEWS) * max(width, height)
    K = np.zeros((VIEWS, 3, 3))
    K[:, 0, 0], K[:, 1, 1] = f, f * rng.uniform(0.97, 1.03, VIEWS)
    K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = (
        width * rng.uniform(0.45, 0.55, VIEWS),
        height * rng.uniform(0.45, 0.55, VIEWS),
        1.0,
    )
    return cam_from_world, K


def _net_depth(k: int, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The known z-depth of view k at network coordinates (x, y) (COLMAP rule): a tilted plane."""
    return 2.0 + 0.001 * x + 0.002 * y + 0.5 * k


def _perfect_outputs(cam_from_world: np.ndarray, K: np.ndarray, transforms) -> dict[str, np.ndarray]:
    """What a perfect MapAnything returns, per the contract, for these cameras (network pixels)."""
    wn, hn = transforms[0].net_size_wh
    ys, xs = np.mgrid[0:hn, 0:wn] + 0.5
    rays, dist, conf = [], [], []
    for k, t in enumerate(transforms):
        K_net = np.diag([t.scale_x, t.scale_y, 1.0]) @ K[k] + np.array(
            [[0, 0, t.offset_x], [0, 0, t.offset_y], [0, 0, 0]]
        )
        d = np.stack([(xs - K_net[0, 2]) / K_net[0, 0], (ys - K_net[1, 2]) / K_net[1, 1], np.ones_like(xs)], axis=-1)
        length = np.linalg.norm(d, axis=-1)
        rays.append(d / length[..., None])
        dist.append(_net_depth(k, xs, ys) * length * METRIC_SCALE)
        conf.append(1 + np.exp(np.sin(xs / 50) + k))
    world_from_cam = invert_pose(cam_from_world)
    quats = matrix_to_quat_xyzw(world_from_cam[:, :3, :3])
    quats[1] *= -1  # q and -q are the same rotation
    return {
        "ray_directions": np.stack(rays)[None].astype(np.float32),
        "depth_along_ray": np.stack(dist)[None, ..., None].astype(np.float32),
        "cam_trans": (world_from_cam[:, :, 3] * METRIC_SCALE)[None].astype(np.float32),
        "cam_quats": quats[None].astype(np.float32),
        "conf": np.stack(conf)[None].astype(np.float32),
        "metric_scaling_factor": np.full((1, VIEWS), METRIC_SCALE, np.float32),
    }


class StandIn(torch.nn.Module):
    """Returns the first S views of fixed tables for an ``images [S, 3, H, W]`` input."""

    def __init__(self, tables: dict[str, np.ndarray]) -> None:
        super().__init__()
        self.names = list(tables)
        for name, value in tables.items():
            self.register_buffer(name, torch.from_numpy(value[0]))

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, ...]:
        s = images.shape[0]
        tie = images.mean() * 0.0  # keeps the input (and its dynamic S) in the graph
        return tuple(getattr(self, name)[:s][None] + tie for name in self.names)


def _export_stand_in(outputs: dict[str, np.ndarray], path: Path) -> Path:
    module = StandIn(outputs).eval()
    example = torch.zeros(2, 3, *outputs["conf"].shape[2:])
    names = list(outputs)
    torch.onnx.export(
        module,
        (example,),
        str(path),
        input_names=["images"],
        output_names=names,
        dynamic_axes={"images": {0: "S"}, **{n: {1: "S"} for n in names}},
        opset_version=17,
        dynamo=False,
    )
    return path


@pytest.fixture(scope="module", params=[(640, 480), (480, 640)], ids=["landscape", "portrait"])
def case(request, tmp_path_factory):
    """Photos, known truth, and the exported stand-in for one orientation."""
    width, height = request.param
    photos = [np.full((height, width, 3), 40 * k, np.uint8) for k in range(VIEWS)]
    _, transforms = preprocess_mapanything(photos)
    cam_from_world, K = _truth(width, height)
    outputs = _perfect_outputs(cam_from_world, K, transforms)
    path = _export_stand_in(outputs, tmp_path_factory.mktemp("mapanything") / f"stand_in_{width}x{height}.onnx")
    return {"photos": photos, "cam_from_world": cam_from_world, "K": K, "path": path, "size_wh": (width, height)}


def test_family_detected_from_names(case):
    model = OnnxModel(case["path"])
    assert model.family is ModelFamily.MAPANYTHING and adapter_for(model.family) is ADAPTER
    assert "ffrecon.contract" not in model.metadata  # detected by the declared names alone


def test_decodes_known_cameras_and_depth(case):
    """Through ffrecon's multi-view loop (preprocess, run at 3 views, decode, validate)."""
    model = OnnxModel(case["path"])
    pred = predict_multiview(
        case["photos"], ["a", "b", "c"], lambda batch: model.run({"images": batch}), model.info(), adapter=ADAPTER
    )
    want = compose_poses(case["cam_from_world"], invert_pose(case["cam_from_world"][0]))  # frame 0 is the world
    want[:, :, 3] *= METRIC_SCALE  # the model's world is metric-scaled
    np.testing.assert_allclose(pred.cam_from_world, want, rtol=TOL, atol=1e-5)
    width, height = case["size_wh"]
    _, transforms = preprocess_mapanything(case["photos"])
    ys, xs = np.mgrid[0:height, 0:width] + 0.5
    for k, t in enumerate(transforms):
        cam = pred.cameras[k]
        assert (cam.width, cam.height) == (width, height)
        np.testing.assert_allclose(cam.K, case["K"][k], rtol=TOL)
        # Original pixel centre (x, y) is network point (s x + offset): the known (metric-scaled) plane's z there.
        xn, yn = xs * t.scale_x + t.offset_x, ys * t.scale_y + t.offset_y
        inside = (xn > 0.5) & (xn < t.net_size_wh[0] - 0.5) & (yn > 0.5) & (yn < t.net_size_wh[1] - 0.5)
        np.testing.assert_allclose(pred.depth[k][inside], METRIC_SCALE * _net_depth(k, xn, yn)[inside], rtol=TOL)
        np.testing.assert_allclose(pred.depth_conf[k][inside], (1 + np.exp(np.sin(xn / 50) + k))[inside], rtol=1e-3)
        cropped = (xn < -0.5) | (xn > t.net_size_wh[0] + 0.5) | (yn < -0.5) | (yn > t.net_size_wh[1] + 0.5)
        assert cropped.any()  # 4:3 photos lose 2 network pixels a side (columns or rows) to the centre crop
        assert (pred.depth[k][cropped] == 0).all() and (pred.depth_conf[k][cropped] == 0).all()


@pytest.mark.parametrize(
    "size_wh,net_hw,scale,offset",
    [
        (
            (640, 480),
            (392, 518),
            (522 / 640, 392 / 480),
            (-2.0, 0.0),
        ),  # shrink (Lanczos) to cover 518x392, crop 2 px a side
        ((480, 640), (518, 392), (392 / 480, 522 / 640), (0.0, -2.0)),
        ((320, 240), (392, 518), (522 / 320, 392 / 240), (-2.0, 0.0)),  # enlarge (bicubic)
        ((1920, 1080), (294, 518), (522 / 1920, 294 / 1080), (-2.0, 0.0)),  # 16:9 -> 1.762 entry
    ],
)
def test_preprocessing_follows_fixed_mapping(size_wh, net_hw, scale, offset):
    """Sizes and offsets of upstream's load_images(resize_mode="fixed_mapping"), worked out by hand."""
    width, height = size_wh
    rng = np.random.default_rng(1)
    photo = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    batch, (t,) = preprocess_mapanything([photo])
    assert batch.shape == (1, 3, *net_hw) and batch.dtype == np.float32 and 0 <= batch.min() and batch.max() <= 1
    assert network_size_hw([width / height]) == net_hw
    np.testing.assert_allclose([t.scale_x, t.scale_y, t.offset_x, t.offset_y], [*scale, *offset])
    from PIL import Image

    new_w, new_h = round(width * scale[0]), round(height * scale[1])
    resample = Image.Resampling.LANCZOS if new_w < width else Image.Resampling.BICUBIC
    want = (
        np.asarray(Image.fromarray(photo).resize((new_w, new_h), resample), np.float32)[
            -int(offset[1]) :, -int(offset[0]) :
        ][: net_hw[0], : net_hw[1]]
        / 255
    )
    np.testing.assert_array_equal(batch[0].transpose(1, 2, 0), want)
    with pytest.raises(ModelError, match="no 'pad' preprocessing"):
        preprocess_mapanything([photo], PreprocessMode.PAD)


def test_bad_outputs_name_the_output():
    photos = [np.zeros((480, 640, 3), np.uint8)] * VIEWS
    _, transforms = preprocess_mapanything(photos)
    cam_from_world, K = _truth(640, 480)
    good = _perfect_outputs(cam_from_world, K, transforms)
    info = ModelInfo("stand-in", ModelFamily.MAPANYTHING)
    with pytest.raises(ModelError, match="lack \\['cam_quats'\\]"):
        decode_mapanything_outputs(
            {k: v for k, v in good.items() if k != "cam_quats"}, transforms, ["a", "b", "c"], info
        )
    with pytest.raises(ModelError, match="'cam_trans' has shape"):
        decode_mapanything_outputs({**good, "cam_trans": good["cam_trans"][:, :2]}, transforms, ["a", "b", "c"], info)
    bad = good["depth_along_ray"].copy()
    bad[0, 1, 5, 5] = np.nan
    with pytest.raises(ModelError, match="'depth_along_ray' has 1 non-finite"):
        decode_mapanything_outputs({**good, "depth_along_ray": bad}, transforms, ["a", "b", "c"], info)
    with pytest.raises(ModelError, match="'cam_quats' has a zero quaternion"):
        decode_mapanything_outputs(
            {**good, "cam_quats": np.zeros_like(good["cam_quats"])}, transforms, ["a", "b", "c"], info
        )
