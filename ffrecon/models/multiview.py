"""Multi-view (VGGT-contract) prediction over any number of frames, in overlapping chunks.

One model call holds at most ``chunk_size`` frames. Each later chunk repeats the last
``chunk_overlap`` frames of the one before; its result is brought into the first chunk's frame and
scale by a Sim(3) fitted on the shared frames' depth points (the same pixels seen in both calls, so
the correspondences are exact), weighted by the model's confidence. Where the path revisits a place,
loop calls and a pose graph close the chain (:mod:`ffrecon.models.loops`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from tqdm.auto import tqdm

from ffrecon.checks import check_number
from ffrecon.errors import InputError, ModelError
from ffrecon.geometry.alignment import Sim3, umeyama
from ffrecon.models.adapters import MultiviewAdapter, PreprocessMode
from ffrecon.models.loops import LoopClosure, LoopOptions, close_loops
from ffrecon.types import ModelInfo, Prediction
from ffrecon.validate import validate_prediction

log = logging.getLogger("ffrecon.models")

# Without a model file to size it from (ffrecon.models.memory picks the default per model and machine).
FALLBACK_CHUNK_SIZE = 8


@dataclass(frozen=True, kw_only=True)
class MultiviewOptions:
    mode: PreprocessMode | None = None  # None: the family's reference preprocessing (its adapter's first mode)
    chunk_size: int | None = None  # frames per model call; None: from the model's size and free memory
    chunk_overlap: int = 2
    max_depth_side: int | None = 1024  # cap on stored depth grids (None: original resolution)
    # The depth and confidence grids of all frames together (float32 each) stay under this: on long captures
    # their long side shrinks below max_depth_side (1,000 frames of 640x480 would hold 2.5 GB). None: no bound.
    depth_memory_gb: float | None = 1.0
    align_points_per_frame: int = 4000  # depth points per shared frame used for the chunk Sim(3)
    loops: LoopOptions = LoopOptions()  # loop calls where the path revisits a place, and the pose graph

    def __post_init__(self) -> None:
        # Consecutive chunks must share a frame (the Sim(3) between them is fitted on it); without a chunk size
        # the overlap is capped at the chosen size less one (ffrecon.models.stage.predict).
        check_number(
            "MultiviewOptions.chunk_size", self.chunk_size, low=2, integer=True, allow_none=True, flag="--chunk-size"
        )
        check_number("MultiviewOptions.chunk_overlap", self.chunk_overlap, low=1, integer=True, flag="--chunk-overlap")
        if self.chunk_size is not None and self.chunk_overlap >= self.chunk_size:
            raise InputError(
                f"--chunk-overlap (MultiviewOptions.chunk_overlap) {self.chunk_overlap} is not less than "
                f"--chunk-size {self.chunk_size}: each chunk must bring at least one new frame",
                f"pass --chunk-overlap at most {self.chunk_size - 1} (at least 1), or a larger --chunk-size",
            )
        check_number("MultiviewOptions.max_depth_side", self.max_depth_side, low=1, integer=True, allow_none=True)
        check_number("MultiviewOptions.depth_memory_gb", self.depth_memory_gb, low=0, low_open=True, allow_none=True)
        check_number("MultiviewOptions.align_points_per_frame", self.align_points_per_frame, low=1, integer=True)


@dataclass(frozen=True)
class ChunkLayout:
    """How the frames were split into model calls and what ran them, for the report."""

    size: int  # frames per call
    overlap: int  # frames shared by consecutive calls
    frames: tuple[tuple[int, int], ...]  # per call, its first and last frame index
    engine: str = "local"  # "local" (this process) or "ray"
    address: str = ""  # Ray's cluster ("local": an instance this run started)
    workers: int = 1  # model sessions
    nodes: int = 1  # machines
    chunk_workers: tuple[str, ...] = ()  # per call, the host:pid that ran it (Ray)
    max_depth_side: int | None = None  # the cap on the stored depth grids' long side (None: photo size)
    loops: LoopClosure | None = None  # the loop pass (None: it did not run)

    @staticmethod
    def of(chunks: Sequence[Sequence[int]], size: int, overlap: int, **engine) -> ChunkLayout:
        return ChunkLayout(size, overlap, tuple((int(c[0]), int(c[-1])) for c in chunks), **engine)

    def to_report(self) -> dict:
        out = {"size": self.size, "overlap": self.overlap, "calls": [list(f) for f in self.frames]}
        out |= {"engine": self.engine, "workers": self.workers, "max_depth_side": self.max_depth_side}
        out["loops"] = None if self.loops is None else self.loops.to_report()
        if self.engine == "ray":
            out |= {"address": self.address, "nodes": self.nodes, "chunk_workers": list(self.chunk_workers)}
        return out


def depth_side_within(options: MultiviewOptions, num_frames: int, width: int, height: int) -> int | None:
    """The cap on the stored depth grids' long side: ``options.max_depth_side``, lowered so that ``num_frames``
    depth and confidence grids (float32) of a ``width`` x ``height`` photo stay under ``options.depth_memory_gb``.

    >>> depth_side_within(MultiviewOptions(), 250, 640, 480)  # 0.6 GB: within the budget
    1024
    >>> depth_side_within(MultiviewOptions(), 1000, 640, 480)  # 2.5 GB at the photo's size
    423
    """
    cap = options.max_depth_side
    if options.depth_memory_gb is None:
        return cap
    scale = np.sqrt(options.depth_memory_gb * 2**30 / (num_frames * width * height * 8))
    if scale >= 1:
        return cap
    side = max(int(max(width, height) * scale), 16)
    return side if cap is None else min(cap, side)


def preprocess_mode(adapter: MultiviewAdapter, options: MultiviewOptions) -> PreprocessMode:
    """The preprocessing asked for, or the family's reference one; a :class:`ModelError` if it has no such mode."""
    mode = options.mode or adapter.modes[0]
    if mode not in adapter.modes:
        raise ModelError(
            f"{adapter.family.value} models have no '{mode.value}' preprocessing",
            f"use --preprocess {' or '.join(m.value for m in adapter.modes)}",
        )
    return mode


def plan_chunks(num_frames: int, chunk_size: int, overlap: int) -> list[list[int]]:
    """Frame indices per model call; consecutive chunks share ``overlap`` frames.

    >>> plan_chunks(10, 4, 2)
    [[0, 1, 2, 3], [2, 3, 4, 5], [4, 5, 6, 7], [6, 7, 8, 9]]
    >>> plan_chunks(3, 16, 4)
    [[0, 1, 2]]
    """
    if num_frames <= chunk_size:
        return [list(range(num_frames))]
    chunks, start = [], 0
    while True:
        end = min(start + chunk_size, num_frames)
        chunks.append(list(range(start, end)))
        if end == num_frames:
            return chunks
        start = end - overlap


def predict_multiview(
    images: Sequence[np.ndarray],
    names: Sequence[str],
    infer: Callable[[np.ndarray], dict[str, np.ndarray]],
    model: ModelInfo,
    options: MultiviewOptions = MultiviewOptions(),
    adapter: MultiviewAdapter | None = None,
) -> Prediction:
    """Run a multi-view model on all frames (chunked, loops closed) and return one :class:`Prediction`.

    Args:
        images: N images ``[H, W, 3]`` uint8 RGB; names: N frame names.
        infer: maps the adapter's input batch ``[S, 3, H, W]`` float32 to the model's outputs.
        adapter: the family's preprocessing and decoding (default: the VGGT contract).
    """
    return predict_multiview_pass(images, names, infer, model, options, adapter)[0]


def predict_multiview_pass(
    images: Sequence[np.ndarray],
    names: Sequence[str],
    infer: Callable[[np.ndarray], dict[str, np.ndarray]],
    model: ModelInfo,
    options: MultiviewOptions = MultiviewOptions(),
    adapter: MultiviewAdapter | None = None,
) -> tuple[Prediction, LoopClosure | None]:
    """:func:`predict_multiview` and what its loop pass did (:func:`~ffrecon.models.loops.close_loops`)."""
    if adapter is None:
        from ffrecon.models.vggt import ADAPTER as adapter
    mode = preprocess_mode(adapter, options)
    chunks = plan_chunks(len(images), *chunking(options))

    def call(frames: Sequence[int]) -> Prediction:
        return predict_chunk(
            [images[k] for k in frames], [names[k] for k in frames], infer, model, mode, adapter, options
        )

    parts = (call(chunk) for chunk in tqdm(chunks, desc="feed-forward", unit="chunk", disable=None))
    merged = merge_chunks(parts, chunks, options.align_points_per_frame)  # each chunk let go once merged
    return with_loops_closed(merged, chunks, lambda calls: [call(c) for c in calls], options)


def with_loops_closed(
    merged: Prediction,
    chunks: Sequence[Sequence[int]],
    run_calls: Callable[[list[list[int]]], Sequence[Prediction]],
    options: MultiviewOptions,
) -> tuple[Prediction, LoopClosure | None]:
    """The merged chunks after the loop pass (``options.loops``); ``run_calls`` runs model calls on lists of
    frame indices, here or on Ray's workers."""

    def fit(ref: Prediction, ref_idx: Sequence[int], new: Prediction, new_idx: Sequence[int]) -> tuple[Sim3, float]:
        return fit_frames(ref, ref_idx, new, new_idx, options.align_points_per_frame)

    return close_loops(merged, chunks, run_calls, fit, options.loops)


def chunking(options: MultiviewOptions) -> tuple[int, int]:
    """``(chunk_size, chunk_overlap)`` as the model calls use them (the overlap capped at the size less one)."""
    size = options.chunk_size or FALLBACK_CHUNK_SIZE
    return size, min(options.chunk_overlap, size - 1)


def predict_chunk(
    images: Sequence[np.ndarray],
    names: Sequence[str],
    infer: Callable[[np.ndarray], dict[str, np.ndarray]],
    model: ModelInfo,
    mode: PreprocessMode,
    adapter: MultiviewAdapter,
    options: MultiviewOptions,
) -> Prediction:
    """One model call on one chunk's frames, decoded and validated (before merging: bad cameras poison the
    chunk Sim(3)). Chunks are independent until :func:`merge_chunks`, so this also runs on other workers."""
    batch, transforms = adapter.preprocess(list(images), mode)
    part = adapter.decode(infer(batch), transforms, list(names), model, options.max_depth_side)
    validate_prediction(part, camera_outputs=adapter.camera_outputs)
    return part


def _sample_points(
    pred: Prediction, k: int, mask: np.ndarray, max_points: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points, confidences and depths at up to ``max_points`` evenly spaced pixels of ``mask``."""
    idx = np.flatnonzero(mask)
    idx = idx[:: max(1, len(idx) // max_points)]
    pts = pred.world_points(k).reshape(-1, 3)[idx]
    return pts, pred.depth_conf[k].reshape(-1)[idx], pred.depth[k].reshape(-1)[idx]


def chunk_alignment(
    ref: Prediction, ref_idx: Sequence[int], new: Prediction, new_idx: Sequence[int], max_points: int
) -> Sim3:
    """Sim(3) ``ref_world_from_new_world`` from frames present in both predictions."""
    return fit_frames(ref, ref_idx, new, new_idx, max_points)[0]


def fit_frames(
    ref: Prediction, ref_idx: Sequence[int], new: Prediction, new_idx: Sequence[int], max_points: int
) -> tuple[Sim3, float]:
    """:func:`chunk_alignment` and its misfit: the median distance of the fitted points from their
    counterparts over the median depth (scale-free; the model's own depth noise sets its floor)."""
    src, dst, weights, depth = [], [], [], []
    for a, b in zip(ref_idx, new_idx):
        mask = ref.valid_mask(a) & new.valid_mask(b)
        if ref.depth[a].shape != new.depth[b].shape or mask.sum() < 3:
            continue
        p_dst, c_dst, z_dst = _sample_points(ref, a, mask, max_points)
        p_src, c_src, _ = _sample_points(new, b, mask, max_points)
        src.append(p_src)
        dst.append(p_dst)
        weights.append(np.sqrt(c_src * c_dst))
        depth.append(z_dst)
    if not src:
        raise ModelError(
            "chunks share no frame with valid depth, so they cannot be put in one frame",
            "increase --chunk-overlap or --chunk-size",
        )
    src_a, dst_a, w = np.concatenate(src), np.concatenate(dst), np.concatenate(weights)
    sim = umeyama(src_a, dst_a, w)
    # One reweighting pass: drop the worst 10% of residuals (depth edges, sky) and refit.
    resid = np.linalg.norm(sim.apply(src_a) - dst_a, axis=1)
    keep = resid <= np.quantile(resid, 0.9)
    if keep.sum() >= 3:
        sim = umeyama(src_a[keep], dst_a[keep], w[keep])
    misfit = np.median(np.linalg.norm(sim.apply(src_a) - dst_a, axis=1)) / max(np.median(np.concatenate(depth)), 1e-12)
    return sim, float(misfit)


def merge_chunks(parts: Iterable[Prediction], chunks: Sequence[Sequence[int]], max_points: int = 4000) -> Prediction:
    """Bring every chunk into the first chunk's world frame and scale; shared frames keep their first estimate.

    ``parts`` (one per chunk, in order) may be a generator: each is merged and dropped before the next."""
    n = max(max(c) for c in chunks) + 1
    poses: list[np.ndarray | None] = [None] * n
    cameras: list = [None] * n
    depth: list = [None] * n
    conf: list = [None] * n
    names: list = [None] * n
    merged_so_far: Prediction | None = None
    merged_index: dict[int, int] = {}  # frame index -> its position in merged_so_far
    for part, chunk in zip(parts, chunks):
        sim = Sim3.identity()
        if merged_so_far is not None:
            shared = [k for k in chunk if poses[k] is not None]
            ref_idx = [merged_index[k] for k in shared]
            sim = chunk_alignment(merged_so_far, ref_idx, part, [chunk.index(k) for k in shared], max_points)
            log.debug("chunk %s: scale %.4f to the first chunk", chunk[:1], sim.scale)
        for local, k in enumerate(chunk):
            if poses[k] is not None:
                continue
            poses[k] = sim.transform_cam_from_world(part.cam_from_world[local])
            cameras[k], names[k] = part.cameras[local], part.names[local]
            depth[k] = part.depth[local] * np.float32(sim.scale)
            conf[k] = part.depth_conf[local]
        done = [k for k in range(n) if poses[k] is not None]
        merged_index = {k: i for i, k in enumerate(done)}
        merged_so_far = Prediction(
            tuple(names[k] for k in done),
            np.stack([poses[k] for k in done]),
            tuple(cameras[k] for k in done),
            tuple(depth[k] for k in done),
            tuple(conf[k] for k in done),
            part.model,
        )
    return merged_so_far
