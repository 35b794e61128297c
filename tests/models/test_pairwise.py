"""The pairwise path: pair graphs, preprocessing bookkeeping, model-output checks, and an end-to-end
run with an exact "oracle" model that answers every pair from an analytic scene."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from ffrecon.errors import FFReconError, InputError, ModelError
from ffrecon.geometry.metrics import pose_errors
from ffrecon.geometry.poses import look_at_cam_from_world, transform_points
from ffrecon.geometry.projection import pixel_centers, unproject_depth
from ffrecon.models.global_alignment import AlignmentOptions, PairPrediction
from ffrecon.models.pairwise import (
    PairGraph,
    PairwiseOptions,
    downsample_pair,
    make_pairs,
    predict_pairwise,
    preprocess_pairwise,
    run_pairs,
)
from ffrecon.types import ModelFamily, ModelInfo

MODEL = ModelInfo("oracle", ModelFamily.PAIRWISE)
TINY_DUST3R = Path(__file__).resolve().parents[2] / "models" / "tiny_dust3r.onnx"


pytestmark = pytest.mark.usefixtures("one_torch_thread")


# ---- pair graphs ---------------------------------------------------------------------------------


def test_complete_graph():
    assert make_pairs(4, PairGraph.COMPLETE, symmetric=False) == [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    pairs = make_pairs(5, PairGraph.COMPLETE)
    assert len(pairs) == 20 and len(set(pairs)) == 20 and all(i != j for i, j in pairs)


def test_sliding_window_graph():
    assert make_pairs(5, PairGraph.SLIDING_WINDOW, window=2, symmetric=False) == [
        (0, 1),
        (0, 2),
        (1, 2),
        (1, 3),
        (2, 3),
        (2, 4),
        (3, 4),
    ]
    cyclic = make_pairs(4, PairGraph.SLIDING_WINDOW, window=1, symmetric=False, cyclic=True)
    assert cyclic == [(0, 1), (1, 2), (2, 3), (3, 0)]
    # A window as long as the sequence is the complete graph; symmetric adds each reverse once.
    assert sorted(make_pairs(4, PairGraph.SLIDING_WINDOW, window=5)) == sorted(make_pairs(4, PairGraph.COMPLETE))
    assert make_pairs(3, PairGraph.SLIDING_WINDOW, window=1) == [(0, 1), (1, 0), (1, 2), (2, 1)]


def test_one_reference_graph():
    assert make_pairs(4, PairGraph.ONE_REFERENCE, reference=2, symmetric=False) == [(2, 0), (2, 1), (2, 3)]
    assert len(make_pairs(4, PairGraph.ONE_REFERENCE)) == 6


def test_pair_graph_errors():
    with pytest.raises(InputError, match="at least 2 views"):
        make_pairs(1, PairGraph.COMPLETE)
    with pytest.raises(FFReconError, match="reference view 5"):
        make_pairs(3, PairGraph.ONE_REFERENCE, reference=5)
    with pytest.raises(FFReconError, match="window"):
        make_pairs(3, PairGraph.SLIDING_WINDOW, window=0)


# ---- preprocessing -------------------------------------------------------------------------------


def _blob_image(height, width, center_xy, sigma=6.0):
    uv = pixel_centers(height, width)
    g = np.exp(-((uv - center_xy) ** 2).sum(-1) / (2 * sigma**2))
    return np.repeat((255 * g)[..., None], 3, axis=2).round().astype(np.uint8)


@pytest.mark.parametrize("size_wh", [(1000, 750), (700, 1000), (1000, 700)])
def test_preprocess_sizes_and_pixel_mapping(size_wh):
    """A Gaussian blob lands where the recorded transform says (COLMAP pixel-centre rule)."""
    w, h = size_wh
    center = np.array([0.43 * w, 0.58 * h])
    batch, (t,) = preprocess_pairwise([_blob_image(h, w, center, sigma=0.02 * max(w, h))])
    hn, wn = batch.shape[2:]
    assert max(hn, wn) <= 512 and hn % 16 == 0 and wn % 16 == 0 and max(hn, wn) > 512 - 16
    assert batch.dtype == np.float32 and batch.min() >= -1 and batch.max() <= 1
    weight = (batch[0, 0] + 1) / 2
    weight = np.where(weight > 0.2, weight, 0)
    found = (pixel_centers(hn, wn) * weight[..., None]).sum((0, 1)) / weight.sum()
    np.testing.assert_allclose(found, t.to_net(center), atol=0.1)
    assert t.orig_size_wh == (w, h) and t.net_size_wh == (wn, hn)


def test_preprocess_common_size_and_forced_size():
    a = np.zeros((300, 400, 3), np.uint8)
    b = np.zeros((400, 300, 3), np.uint8)  # portrait: scaled to cover the landscape size, then cropped
    batch, (ta, tb) = preprocess_pairwise([a, b], long_side=128)
    assert batch.shape == (2, 3, 96, 128)
    assert tb.net_size_wh == (128, 96) and tb.scale_x == pytest.approx(128 / 300, rel=0.01) and tb.offset_y < 0
    batch, _ = preprocess_pairwise([a, b], size_hw=(224, 224))
    assert batch.shape == (2, 3, 224, 224)
    with pytest.raises(InputError, match="multiple of 16"):
        preprocess_pairwise([a], size_hw=(100, 128))
    with pytest.raises(InputError, match="uint8"):
        preprocess_pairwise([a.astype(np.float32)])


# ---- running pairs -------------------------------------------------------------------------------


def _tagging_model(calls):
    """Fake model: each output is filled with the index tags painted into the views."""

    def infer(view1, view2):
        calls.append(len(view1))
        tag1, tag2 = view1[:, 0, 0, 0], view2[:, 0, 0, 0]
        b, _, h, w = view1.shape
        ones3, ones = np.ones((b, h, w, 3), np.float32), np.ones((b, h, w), np.float32)
        return {
            "pts3d": ones3 * tag1[:, None, None, None],
            "conf": ones + tag1[:, None, None] + 1,
            "pts3d_in_other_view": ones3 * tag2[:, None, None, None],
            "conf_in_other_view": ones + tag2[:, None, None] + 1,
        }

    return infer


def test_run_pairs_batches_and_orders_outputs():
    batch = np.zeros((4, 3, 16, 32), np.float32)
    batch[:, 0, 0, 0] = [0.0, 0.1, 0.2, 0.3]  # tags
    pairs = make_pairs(4, PairGraph.COMPLETE)
    calls = []
    preds = run_pairs(batch, pairs, _tagging_model(calls), batch_size=5)
    assert calls == [5, 5, 2]
    assert [(p.i, p.j) for p in preds] == pairs
    for p in preds:
        assert p.pts_i_in_i.shape == (16, 32, 3) and p.conf_j.shape == (16, 32)
        assert p.pts_i_in_i[0, 0, 0] == pytest.approx(0.1 * p.i) and p.pts_j_in_i[0, 0, 0] == pytest.approx(0.1 * p.j)


@pytest.mark.parametrize(
    "spoil, message",
    [
        (lambda out: out["pts3d_in_other_view"].__setitem__((0, 3, 4, 1), np.nan), "non-finite"),
        (lambda out: out["conf"].__setitem__((0, 0, 0), np.inf), "non-finite"),
        (lambda out: out.pop("conf_in_other_view"), "lack"),
        (lambda out: out.__setitem__("conf", out["conf"] - 2.5), "confidences must be >= 1"),
        (lambda out: out.__setitem__("pts3d", out["pts3d"][:, :8]), "shape"),
    ],
)
def test_run_pairs_rejects_bad_outputs(spoil, message):
    batch = np.zeros((2, 3, 16, 32), np.float32)
    good = _tagging_model([])

    def infer(view1, view2):
        out = dict(good(view1, view2))
        spoil(out)
        return out

    with pytest.raises(ModelError, match=message):
        run_pairs(batch, [(0, 1), (1, 0)], infer)


def test_downsample_pair_keeps_planar_points_at_block_centres():
    """A fronto-parallel plane: block means of points are exactly the points at the coarse pixel centres."""
    h, w, f = 16, 24, 20.0
    pts = unproject_depth(np.full((h, w), 2.0), np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])).astype(np.float32)
    conf = np.full((h, w), 3.0, np.float32)
    coarse = downsample_pair(PairPrediction(0, 1, pts, conf, pts, conf), 4)
    expected = unproject_depth(
        np.full((h // 4, w // 4), 2.0), np.array([[f / 4, 0, w / 8], [0, f / 4, h / 8], [0, 0, 1]])
    )
    np.testing.assert_allclose(coarse.pts_i_in_i, expected, atol=1e-6)
    assert coarse.conf_j.shape == (4, 6)


# ---- end to end with an exact model --------------------------------------------------------------


def _room_depth(cam_from_world, K, size_hw):
    """Exact z-depth in the box room [-3, 3]^3 around a sphere of radius 0.7 at the origin
    (pixel centres, COLMAP rule)."""
    h, w = size_hw
    center = -cam_from_world[:, :3].T @ cam_from_world[:, 3]
    uv = pixel_centers(h, w)
    dirs = np.concatenate([(uv - K[:2, 2]) / [K[0, 0], K[1, 1]], np.ones((h, w, 1))], axis=-1) @ cam_from_world[:, :3]
    t = np.full((h, w), np.inf)
    for axis in range(3):
        for sign in (1.0, -1.0):
            along = sign * dirs[..., axis]
            t = np.where(
                along > 1e-9, np.minimum(t, (3.0 - sign * center[axis]) / np.where(along > 1e-9, along, 1.0)), t
            )
    a, b, c = (dirs**2).sum(-1), (dirs * center).sum(-1), center @ center - 0.7**2
    t_sphere = (-b - np.sqrt(np.maximum(b**2 - a * c, 0.0))) / a
    return np.where((b**2 - a * c > 0) & (t_sphere > 0), np.minimum(t, t_sphere), t)


def test_predict_pairwise_with_an_exact_model_recovers_original_cameras():
    """Photos 136x100 -> network 96x64 (resize and crop) -> alignment on 48x32 blocks -> photo pixels."""
    rng = np.random.default_rng(0)
    n, photo_hw = 4, (100, 136)
    photos = [rng.integers(0, 256, (*photo_hw, 3), dtype=np.uint8) for _ in range(n)]
    options = PairwiseOptions(
        graph=PairGraph.SLIDING_WINDOW, window=2, long_side=96, batch_size=3, alignment=AlignmentOptions(iterations=200)
    )
    batch, transforms = preprocess_pairwise(photos, options.long_side)
    net_h, net_w = batch.shape[2:]
    # Ground truth lives in network pixels, with the principal point at the centre as the model assumes.
    poses, K_net = [], []
    for k in range(n):
        angle = 0.35 * k
        poses.append(
            look_at_cam_from_world(
                np.array([1.8 * np.cos(angle), 1.8 * np.sin(angle), 0.3 * k - 0.4]), rng.normal(0, 0.2, 3)
            )
        )
        f = rng.uniform(0.8, 1.1) * net_w
        K_net.append(np.array([[f, 0, net_w / 2], [0, f, net_h / 2], [0, 0, 1.0]]))
    poses = np.stack(poses)
    depth = [_room_depth(poses[k], K_net[k], (net_h, net_w)) for k in range(n)]
    world = [unproject_depth(depth[k], K_net[k], poses[k]) for k in range(n)]

    def oracle(view1, view2):
        def index(view):
            return int(np.flatnonzero([np.array_equal(view, b) for b in batch])[0])

        out = {name: [] for name in ("pts3d", "conf", "pts3d_in_other_view", "conf_in_other_view")}
        for v1, v2 in zip(view1, view2):
            i, j = index(v1), index(v2)
            scale = 0.7 + 0.1 * (i + 2 * j)
            out["pts3d"].append(unproject_depth(depth[i], K_net[i]) * scale)
            out["pts3d_in_other_view"].append(transform_points(poses[i], world[j]) * scale)
            out["conf"].append(np.full((net_h, net_w), 3.0))
            out["conf_in_other_view"].append(np.full((net_h, net_w), 2.0))
        return {k: np.stack(v).astype(np.float32) for k, v in out.items()}

    pred = predict_pairwise(photos, [f"{k}.png" for k in range(n)], oracle, MODEL, options)
    assert pred.names == ("0.png", "1.png", "2.png", "3.png") and pred.model.family is ModelFamily.PAIRWISE
    errors = pose_errors(pred.cam_from_world, poses)
    assert errors.auc[5] >= 0.99
    np.testing.assert_allclose(pred.cam_from_world[0], np.eye(3, 4), atol=1e-9)
    for k in range(n):
        K_photo = transforms[k].K_to_original(K_net[k])
        cam = pred.cameras[k]
        assert (cam.width, cam.height) == (photo_hw[1], photo_hw[0])
        np.testing.assert_allclose([cam.fx, cam.fy], [K_photo[0, 0], K_photo[1, 1]], rtol=0.01)
        np.testing.assert_allclose([cam.cx, cam.cy], K_photo[:2, 2], atol=1e-9)
        # Depth in photo pixels against the exact depth there; 0 only in the rows the crop removed.
        truth = _room_depth(poses[k], K_photo, photo_hw).astype(np.float32)
        known = pred.depth[k] > 0
        rows_kept = np.flatnonzero(known.any(axis=1))
        assert known[rows_kept[0] + 1 : rows_kept[-1]].all() and len(rows_kept) >= 0.85 * photo_hw[0]
        rel = np.abs(pred.depth[k] * errors.est_to_ref.scale / truth - 1)
        assert np.median(rel[known]) < 0.01
        # Away from the sphere's outline (bilinear resampling blurs depth edges) and the image border.
        smooth = cv2.dilate(truth, np.ones((7, 7))) < 1.1 * cv2.erode(truth, np.ones((7, 7)))
        inner = np.zeros_like(known)
        inner[rows_kept[0] + 2 : rows_kept[-1] - 1, 2:-2] = True
        assert rel[inner & smooth].max() < 0.02 and (inner & smooth).mean() > 0.5
        assert (pred.depth_conf[k][known] >= 1).all() and (pred.depth_conf[k][~known] == 0).all()


@pytest.mark.skipif(
    not TINY_DUST3R.is_file(), reason="models/tiny_dust3r.onnx is not built yet (another developer's fixture)"
)
def test_tiny_dust3r_onnx_smoke():
    from ffrecon.models.runner import OnnxModel

    model = OnnxModel(TINY_DUST3R, threads=1)
    assert model.family is ModelFamily.PAIRWISE
    view_shape = next(i.shape for i in model.inputs if i.name == "view1")
    size_hw = tuple(view_shape[2:]) if all(isinstance(d, int) for d in view_shape[2:]) else None
    rng = np.random.default_rng(0)
    photos = [rng.integers(0, 256, (120, 160, 3), dtype=np.uint8) for _ in range(3)]
    options = PairwiseOptions(long_side=64, size_hw=size_hw, alignment=AlignmentOptions(iterations=20))
    pred = predict_pairwise(
        photos, ["a", "b", "c"], lambda v1, v2: model.run({"view1": v1, "view2": v2}), model.info(), options
    )
    assert len(pred) == 3 and np.isfinite(pred.cam_from_world).all()
    assert all(c.fx > 0 and (c.width, c.height) == (160, 120) for c in pred.cameras)
    assert all(np.isfinite(d).all() and (d >= 0).all() for d in pred.depth)
