"""The feed-forward pose stage: ONNX model in, cameras, depth and point maps out."""

from __future__ import annotations

import contextlib
import dataclasses
import logging
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ffrecon.capture import Capture
from ffrecon.checks import check_number
from ffrecon.colmap_io import reconstruction_from_cameras, write_reconstruction
from ffrecon.concurrency import CoreShare
from ffrecon.errors import InputError
from ffrecon.formats.pointcloud import FrameClouds, FuseOptions, fuse_prediction_frames, write_depth_maps
from ffrecon.geometry.alignment import umeyama
from ffrecon.geometry.poses import camera_centers
from ffrecon.models.adapters import adapter_for
from ffrecon.models.distributed import RayOptions
from ffrecon.models.memory import default_chunk_size
from ffrecon.models.multiview import (
    ChunkLayout,
    MultiviewOptions,
    chunking,
    depth_side_within,
    merge_chunks,
    plan_chunks,
    predict_multiview_pass,
    preprocess_mode,
    with_loops_closed,
)
from ffrecon.models.pairwise import PairwiseOptions
from ffrecon.models.runner import OnnxModel, cpu_threads
from ffrecon.timing import StageTimer, Timings
from ffrecon.types import ModelFamily, ModelInfo, PinholeCamera, Prediction
from ffrecon.validate import validate_prediction

log = logging.getLogger("ffrecon.models")
# The fusion's frames (FeedForwardResult.frame_clouds) are kept for the exports up to this size (about 40 MB at 96
# frames of 640x480); larger, the exports fuse the depth maps again.
KEEP_FRAME_CLOUDS_BYTES = 512 * 2**20
# The photos the network read are kept for the fusion up to this size (the first frames read; the rest are read
# again): 250 frames of 640x480, or 7 of 12 MP
KEEP_PHOTO_BYTES = 256 * 2**20


@dataclass(frozen=True, kw_only=True)
class FeedForwardOptions:
    threads: int | None = None  # onnxruntime intra-op threads (None: all cores)
    multiview: MultiviewOptions = field(default_factory=MultiviewOptions)
    pairwise: PairwiseOptions = field(default_factory=PairwiseOptions)
    fuse: FuseOptions = field(default_factory=FuseOptions)
    ray: RayOptions | None = None  # run the model's chunks on Ray (local instance or cluster); None: in this process

    def __post_init__(self) -> None:
        check_number("FeedForwardOptions.threads", self.threads, low=1, integer=True, allow_none=True, flag="--threads")


@dataclass(frozen=True)
class FeedForwardResult:
    prediction: Prediction
    points_xyz: np.ndarray  # [M, 3] fused, world frame of the model
    points_rgb: np.ndarray  # [M, 3] float in [0, 1]
    sparse_dir: Path
    providers: tuple[str, ...]
    assumptions: str = ""  # what decoding had to assume (monocular depth), for the report
    # The model's own intrinsics where the user gave them (--intrinsics): the prediction holds the given ones.
    model_cameras: tuple[PinholeCamera, ...] = ()
    # The model's own poses where the user gave poses (--poses): the prediction holds the given ones.
    model_poses: np.ndarray | None = None  # [N, 3, 4] cam_from_world
    chunks: ChunkLayout | None = None  # multi-view families: how the frames were split into model calls
    timings: Timings = field(default_factory=Timings)  # the stage's steps (wall and CPU seconds); empty: not timed
    # The fusion's frames, each reduced alone (see FrameClouds), so that the exports fuse them again with refined
    # cameras without a second pass over the depth maps and photos. Not part of the stage's record (init=False):
    # None in a resumed run, or when larger than KEEP_FRAME_CLOUDS_BYTES.
    frame_clouds: FrameClouds | None = field(default=None, init=False, compare=False, repr=False)

    def to_report(self) -> dict:
        m = self.prediction.model
        return {
            "model": {
                "path": m.path,
                "family": m.family.value,
                "simulated": m.simulated,
                "description": m.description,
                "providers": list(self.providers),
                "notes": m.metadata.get("ffrecon.notes", ""),
            },
            "world_frame": _world_frame(m),
            "assumptions": self.assumptions,
            "num_frames": len(self.prediction),
            "num_points": int(len(self.points_xyz)),
            "cameras": [
                {"name": n, "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "width": c.width, "height": c.height}
                for n, c in zip(self.prediction.names, self.prediction.cameras)
            ],
            **({"model_cameras": _model_cameras(self.prediction, self.model_cameras)} if self.model_cameras else {}),
            **({"chunks": self.chunks.to_report()} if self.chunks is not None else {}),
            **(
                {"timings_s": self.timings.to_report(), "cpu_s": self.timings.cpu_report()}
                if self.timings.stages
                else {}
            ),
        }


def _model_cameras(prediction: Prediction, model_cameras: tuple[PinholeCamera, ...]) -> list[dict]:
    """The model's own estimate beside the given intrinsics, per frame: its focal and how far it is from them."""
    return [
        {"name": n, "fx": m.fx, "fy": m.fy, "cx": m.cx, "cy": m.cy, "focal_vs_given": m.fx / c.fx - 1.0}
        for n, m, c in zip(prediction.names, model_cameras, prediction.cameras)
    ]


def _world_frame(model: ModelInfo) -> str:
    if model.family is ModelFamily.PAIRWISE:
        return "the first photo's camera (global alignment of the pairs)"
    if model.simulated:
        return "the first frame's camera"
    return adapter_for(model.family).world_frame


def _assumptions(model: ModelInfo, capture: Capture) -> str:
    """What the decoding had to assume, for the report (monocular depth: scale and the focal length)."""
    if model.family is not ModelFamily.MONODEPTH:
        return ""
    from ffrecon.models import monodepth

    return monodepth.describe_assumptions(
        model.metadata.get("ffrecon.depth_kind", "relative_inverse"), capture.frames[0].focal_prior_px
    )


@dataclass(frozen=True)
class ModelPass:
    prediction: Prediction  # validated
    chunks: ChunkLayout | None = None  # multi-view families: the model calls


def predict(model: OnnxModel, capture: Capture, images: Sequence[np.ndarray], options: FeedForwardOptions) -> ModelPass:
    """Run the model's family adapter on every frame of the capture; the result is validated."""
    names = list(capture.names)
    if options.ray is not None and model.family in (ModelFamily.PAIRWISE, ModelFamily.MONODEPTH):
        log.warning("--ray runs a multi-view model's chunks; this %s model runs here", model.family.value)
    if model.family is ModelFamily.PAIRWISE:  # every pair reads its two photos: read each once, here
        prediction = _predict_pairwise(model, list(images), names, options)
        validate_prediction(
            prediction, camera_outputs="pts3d/pts3d_in_other_view (after global alignment)", depth_outputs="pts3d"
        )
        return ModelPass(prediction)
    if model.family is ModelFamily.MONODEPTH:
        return ModelPass(_predict_monodepth(model, capture, images, names, options))
    return _predict_multiview(model, images, names, options)


def _predict_monodepth(
    model: OnnxModel, capture: Capture, images: Sequence[np.ndarray], names: list[str], options: FeedForwardOptions
) -> Prediction:
    from ffrecon.models import monodepth

    if len(images) != 1:
        raise InputError(
            f"{model.path.name} is a monocular depth model (one image in, depth out), "
            f"but the input has {len(images)} images",
            "pass one photo, or use a multi-view model (VGGT, Depth Anything 3, Pi3) "
            "or a pairwise one (DUSt3R, MASt3R) for several",
        )
    adapter = monodepth.ADAPTER
    infer = lambda batch: model.run_checked(adapter.input_name, {adapter.input_name: batch})  # noqa: E731
    prediction = monodepth.predict_monodepth(
        images[0],
        names[0],
        infer,
        model.info(),
        focal_px=capture.frames[0].focal_prior_px,
        max_depth_side=options.multiview.max_depth_side,
    )
    validate_prediction(prediction, camera_outputs="(EXIF focal or the stated guess)", depth_outputs="predicted_depth")
    return prediction


def _predict_multiview(
    model: OnnxModel, images: Sequence[np.ndarray], names: list[str], options: FeedForwardOptions
) -> ModelPass:
    """Chunked model calls, in this process or on Ray's workers (``options.ray``), merged here."""
    adapter = adapter_for(model.family)
    mv_options = options.multiview
    if mv_options.chunk_size is None:
        size_hw = tuple(adapter.preprocess(images[:1], mv_options.mode or adapter.modes[0])[0].shape[-2:])
        chunk = default_chunk_size(model.path, size_hw, model.metadata, on_cuda=model.on_cuda)
        mv_options = dataclasses.replace(
            mv_options, chunk_size=chunk, chunk_overlap=min(mv_options.chunk_overlap, chunk - 1)
        )
    mv_options = _within_depth_memory(mv_options, images)
    chunks = plan_chunks(len(images), *chunking(mv_options))
    if options.ray is not None:
        from ffrecon.models.distributed import predict_chunks_ray

        mode = preprocess_mode(adapter, mv_options)

        def on_ray(calls: Sequence[Sequence[int]]) -> tuple[Prediction, ...]:
            return predict_chunks_ray(model.info(), images, names, calls, mode, mv_options, options.ray).parts

        ray = predict_chunks_ray(model.info(), images, names, chunks, mode, mv_options, options.ray)
        merged = merge_chunks(ray.parts, chunks, mv_options.align_points_per_frame)
        prediction, loops = with_loops_closed(merged, chunks, on_ray, mv_options)
        return ModelPass(
            prediction, dataclasses.replace(ray.layout, max_depth_side=mv_options.max_depth_side, loops=loops)
        )
    infer = lambda batch: model.run_checked(adapter.input_name, {adapter.input_name: batch})  # noqa: E731
    prediction, loops = predict_multiview_pass(images, names, infer, model.info(), mv_options, adapter)
    layout = ChunkLayout.of(chunks, *chunking(mv_options), max_depth_side=mv_options.max_depth_side, loops=loops)
    return ModelPass(prediction, layout)


def _within_depth_memory(options: MultiviewOptions, images: Sequence[np.ndarray]) -> MultiviewOptions:
    """``options`` with the depth grids' cap lowered to keep every frame's depth within the memory bound
    (sized on the first frame)."""
    height, width = images[0].shape[:2]
    side = depth_side_within(options, len(images), width, height)
    if side != options.max_depth_side:
        log.info(
            "depth grids stored at %d px on the long side: %d frames of %dx%d stay within %.1f GB",
            side,
            len(images),
            width,
            height,
            options.depth_memory_gb,
        )
    return dataclasses.replace(options, max_depth_side=side)


def _predict_pairwise(model: OnnxModel, images: list, names: list, options: FeedForwardOptions) -> Prediction:
    from ffrecon.models import pairwise

    pw_options = options.pairwise
    fixed = model.fixed_size_hw("view1")
    if fixed is not None and pw_options.size_hw is None:  # exports bake H and W in: resize to them
        pw_options = dataclasses.replace(pw_options, size_hw=fixed)
    infer = lambda v1, v2: model.run_checked("view1", {"view1": v1, "view2": v2})  # noqa: E731
    if len(images) > 1:
        return pairwise.predict_pairwise(images, names, infer, model.info(), pw_options)
    # One photo: pair it with itself (what DUSt3R's own demo does) and keep the first view.
    log.info("one photo with a pairwise model: pairing it with itself")
    both = pairwise.predict_pairwise(images * 2, [names[0], names[0] + "#self"], infer, model.info(), pw_options)
    return Prediction(
        both.names[:1], both.cam_from_world[:1], both.cameras[:1], both.depth[:1], both.depth_conf[:1], both.model
    )


def run_feedforward(
    capture: Capture,
    model_path: Path,
    options: FeedForwardOptions,
    out_dir: Path,
    *,
    while_inferring: Callable[[], AbstractContextManager] = contextlib.nullcontext,
) -> FeedForwardResult:
    """Predict, then write ``out_dir/feedforward/{sparse,depth}`` and return the prediction.

    The frames are read from the capture's ``images/`` here and released when the stage ends.
    ``while_inferring`` is entered around each run of the network (see :class:`OnnxModel`).
    """
    timer = StageTimer()  # the stage's steps, in report.json's feedforward.timings_s and cpu_s
    with timer.stage("load_model"):
        model = OnnxModel(model_path, threads=options.threads or 0, while_running=while_inferring)
    log.info(
        "feed-forward model %s (%s%s) on %d frames",
        Path(model_path).name,
        model.family.value,
        ", SIMULATED" if model.simulated else "",
        len(capture.frames),
    )
    # each read when a model call asks for it, and kept for the fusion (and the loop calls) while they fit in
    # KEEP_PHOTO_BYTES: 96 frames of 640x480 (88 MB) were decoded 2.3 times each in --quick (0.9 CPU s, issue 40)
    images = capture.frames_on_demand(keep_bytes=KEEP_PHOTO_BYTES)
    with timer.stage("predict"):  # reading and resizing the photos, the network's calls, merging its chunks
        model_pass = predict(model, capture, images, options)
    with timer.stage("given_and_masks"):
        prediction, model_cameras, model_poses = _given_and_masked(model_pass.prediction, capture)
    with timer.stage("fuse"):
        xyz, rgb, clouds = fuse_prediction_frames(prediction, images, options.fuse)
    ff_dir = Path(out_dir) / "feedforward"
    with timer.stage("write_sparse"):
        rec = reconstruction_from_cameras(prediction.names, prediction.cam_from_world, prediction.cameras, xyz, rgb)
        sparse_dir = write_reconstruction(rec, ff_dir / "sparse")
    with timer.stage("write_depth"):
        write_depth_maps(ff_dir / "depth", prediction)
    info = (model.providers, _assumptions(model.info(), capture), model_cameras, model_poses, model_pass.chunks)
    with timer.stage("release"):  # onnxruntime's session and the photos read, freed here rather than on return
        del model, images, model_pass
    timer.close()
    result = FeedForwardResult(prediction, xyz, rgb, sparse_dir, *info, timings=timer.freeze())
    if clouds is not None and clouds.nbytes <= KEEP_FRAME_CLOUDS_BYTES:
        object.__setattr__(result, "frame_clouds", clouds)  # frozen: set once, here
    return result


def _given_and_masked(
    prediction: Prediction, capture: Capture
) -> tuple[Prediction, tuple[PinholeCamera, ...], np.ndarray | None]:
    """``(prediction, model_cameras, model_poses)``: the user's intrinsics and poses in place of the model's
    (the model's kept for the report: empty and None when none were given), masked pixels without confidence."""
    model_cameras = ()
    if capture.known_cameras:  # the user's intrinsics replace the model's estimate (kept for the report)
        model_cameras = prediction.cameras
        prediction = dataclasses.replace(prediction, cameras=_known_at(capture.known_cameras, model_cameras))
        _log_given(prediction, model_cameras)
    model_poses = None
    if capture.known_poses:  # the user's poses replace the model's, moved into its frame (kept for the report)
        model_poses = prediction.cam_from_world
        prediction = dataclasses.replace(prediction, cam_from_world=given_poses_in(model_poses, capture.known_poses))
    masks = capture.read_masks()
    if masks is not None:  # masked pixels carry no confidence: no fused point, seed or dense evidence from them
        prediction = masked_prediction(prediction, masks)
    return prediction, model_cameras, model_poses


def given_poses_in(model_poses: np.ndarray, given: tuple[np.ndarray | None, ...]) -> np.ndarray:
    """The given poses (None: keep the model's) in the model's world frame and scale: moved by the Sim(3)
    that best maps the given camera centres onto the model's (Umeyama), so depth maps and poses agree."""
    have = [k for k, p in enumerate(given) if p is not None]
    poses = np.stack([given[k] for k in have])
    sim = umeyama(camera_centers(poses), camera_centers(model_poses[have]))
    out = np.array(model_poses, np.float64, copy=True)
    out[have] = sim.transform_cam_from_world(poses)
    log.info(
        "the given poses replace the model's for %d of %d frames (moved into its frame: scale %.4g)",
        len(have),
        len(given),
        sim.scale,
    )
    return out


def masked_prediction(prediction: Prediction, masks: list[np.ndarray]) -> Prediction:
    """``prediction`` with no depth (0, unknown) and no confidence where ``masks`` (``[H, W]`` bool per frame
    at the photo's size, True: use) say to ignore a pixel, so that no fused point, splat seed or dense
    evidence comes from there (:meth:`Prediction.valid_mask`); each mask is resized (nearest) to its depth
    map's grid."""
    depths, confs = [], []
    for depth, conf, mask in zip(prediction.depth, prediction.depth_conf, masks):
        h, w = depth.shape
        if mask.shape != (h, w):
            mask = cv2.resize(mask.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
        depths.append(np.where(mask, depth, 0).astype(depth.dtype))
        confs.append(np.where(mask, conf, 0).astype(conf.dtype))
    return dataclasses.replace(prediction, depth=tuple(depths), depth_conf=tuple(confs))


def _known_at(known: tuple[PinholeCamera, ...], predicted: tuple[PinholeCamera, ...]) -> tuple[PinholeCamera, ...]:
    """The given cameras at the size of the model's (the frames as captured; scaled when they differ)."""
    return tuple(
        k if (k.width, k.height) == (p.width, p.height) else k.scaled(p.width / k.width, p.height / k.height)
        for k, p in zip(known, predicted)
    )


def _log_given(prediction: Prediction, model_cameras: tuple[PinholeCamera, ...]) -> None:
    moved = np.array([m.fx / c.fx - 1.0 for m, c in zip(model_cameras, prediction.cameras)])
    log.info(
        "the given intrinsics replace the model's (its focal lengths differ by %+.1f%% median, %.1f%% at most)",
        100 * float(np.median(moved)),
        100 * float(np.abs(moved).max()),
    )


def feedforward_skip_reason(model: Path | None, num_frames: int, *, colmap: bool) -> str | None:
    """Why the feed-forward stage does not run (no model given), or None; an :class:`InputError` when
    without a model nothing would make the cameras (one photo, or ``colmap`` turned off)."""
    if model is not None:
        return None
    if num_frames < 2:
        raise InputError("one photo and no model: nothing can place a camera", "pass --model, or more photos")
    if not colmap:
        raise InputError("no model and --no-colmap: nothing would make the cameras", "pass --model or drop --no-colmap")
    return "no model given (--model): the cameras come from COLMAP and the splat is seeded from its points"


def run_feedforward_sharing(
    capture: Capture, model: Path, options: FeedForwardOptions, out_dir: Path, cores: CoreShare | None
) -> FeedForwardResult:
    """:func:`run_feedforward`, claiming its CPU threads in ``cores`` while it runs beside another stage
    (None: alone).

    One core for the stage's own thread throughout (reading, decoding, fusing, writing), and the rest of
    onnxruntime's threads only while the network runs: with a small or simulated network most of the
    stage is that one thread, and COLMAP's extraction (asking per batch) takes the other core.
    """
    if cores is None:
        return run_feedforward(capture, model, options, out_dir)
    extra = cpu_threads(options.threads) - 1
    with cores.claim(1):
        return run_feedforward(capture, model, options, out_dir, while_inferring=lambda: cores.claim(extra))
