"""Loop chunks: where a long path revisits a place, one more model call sees both ends and closes the chain.

Chunks are chained by a Sim(3) fitted on their shared frames (:func:`~ffrecon.models.multiview.merge_chunks`);
a model whose error grows along its input drifts a little at every link, and over hundreds of frames the
revisit no longer meets the start. Here:

1. each chunk's first, middle and last frame are key frames; the merged cameras and depth say which key
   frames of chunks at least ``min_chunk_gap`` calls apart see the same surfaces (:func:`~ffrecon.geometry.
   overlap.overlap_matrix`): the revisits. The farthest apart of them, no two joining the same stretches,
   become loop calls, each holding frames around both key frames;
2. a loop call holds frames of both chunks; its Sim(3) to the chain fitted on each end's frames says how
   the chain should close there (the two fits agree when there is no drift);
3. a Sim(3) pose graph (:mod:`ffrecon.geometry.pose_graph`) over one correction per chunk, with the chain's
   links (which the merge made exact) and the loops as edges, spreads the disagreement along the chain;
   every frame takes its chunk's correction.

A loop call whose ends fit the chain poorly (the model could not place the two ends together) or that would
turn the chain by more than ``max_closure_deg`` (a revisit misread) is left out, and the report says so.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from ffrecon.checks import check_number
from ffrecon.errors import ModelError
from ffrecon.geometry.alignment import Sim3
from ffrecon.geometry.overlap import overlap_matrix
from ffrecon.geometry.pose_graph import PoseGraphOptions, Sim3Edge, optimize_pose_graph
from ffrecon.geometry.rotations import rotation_angle_deg
from ffrecon.types import Prediction

log = logging.getLogger("ffrecon.models")


@dataclass(frozen=True, kw_only=True)
class LoopOptions:
    enabled: bool = True
    min_overlap: float = 0.3  # two key frames whose predicted overlap (both ways) reaches this: a revisit
    min_chunk_gap: int = 6  # ... when their chunks are at least this many calls apart (nearer: little drift between)
    max_loops: int = 8  # loop calls at most (the best revisits, no two within min_chunk_gap at both ends)
    frames_per_end: int = 4  # frames of each end in a loop call (at most half the chunk size)
    max_misfit: float = 0.05  # an end whose points fit the chain worse (median distance / depth): loop dropped
    max_closure_deg: float = 30.0  # a loop that would turn the chain by more is not trusted
    pose_graph: PoseGraphOptions = PoseGraphOptions()

    def __post_init__(self) -> None:
        check_number("LoopOptions.min_overlap", self.min_overlap, low=0, high=1, low_open=True)
        check_number("LoopOptions.min_chunk_gap", self.min_chunk_gap, low=2, integer=True)
        check_number("LoopOptions.max_loops", self.max_loops, low=0, integer=True)
        check_number("LoopOptions.frames_per_end", self.frames_per_end, low=1, integer=True)
        check_number("LoopOptions.max_misfit", self.max_misfit, low=0, low_open=True)
        check_number("LoopOptions.max_closure_deg", self.max_closure_deg, low=0, high=180, low_open=True)


@dataclass(frozen=True)
class LoopCall:
    """One loop call: the frames it held, the chunks it joins, and how the chain met it."""

    frames: tuple[int, ...]
    chunks: tuple[int, int]
    overlap: float  # the key frames' predicted overlap that proposed it
    misfit: tuple[float, float]  # each end's fit to the chain (median point distance / median depth)
    closure_deg: float  # rotation by which the chain missed this loop before the pose graph
    closure_scale: float  # scale ratio by which it missed
    used: bool  # False: left out (misfit or closure over the bounds)
    b_from_a: Sim3 = field(default_factory=Sim3.identity, repr=False, compare=False)  # the edge it gives

    def to_report(self) -> dict:
        return {
            "frames": list(self.frames),
            "chunks": list(self.chunks),
            "overlap": round(self.overlap, 4),
            "misfit": [round(m, 5) for m in self.misfit],
            "closure_deg": round(self.closure_deg, 4),
            "closure_scale": round(self.closure_scale, 5),
            "used": self.used,
        }


@dataclass(frozen=True)
class LoopClosure:
    """What the loop pass found and did, for ``report.json`` (``feedforward.chunks.loops``)."""

    candidates: int  # chunk pairs whose key frames overlap enough
    calls: tuple[LoopCall, ...]
    iterations: int = 0  # pose-graph iterations (0: no pose graph ran)
    max_correction_deg: float = 0.0  # the largest chunk rotation the pose graph applied
    max_correction_scale: float = 1.0  # the largest chunk scale change (ratio >= 1 either way)
    error: str | None = None  # why the pass stopped short (a loop call the model failed on), if it did

    def to_report(self) -> dict:
        return {
            "candidates": self.candidates,
            "calls": [c.to_report() for c in self.calls],
            "pose_graph_iterations": self.iterations,
            "max_correction_deg": round(self.max_correction_deg, 4),
            "max_correction_scale": round(self.max_correction_scale, 5),
            "error": self.error,
        }


def owners(chunks: Sequence[Sequence[int]], num_frames: int) -> np.ndarray:
    """``[N]`` the chunk whose estimate each frame kept in the merge: the first that held it.

    >>> owners([[0, 1, 2], [1, 2, 3], [2, 3, 4]], 5).tolist()
    [0, 0, 0, 1, 2]
    """
    out = np.full(num_frames, -1, np.int64)
    for c, chunk in reversed(list(enumerate(chunks))):
        out[list(chunk)] = c
    return out


def _key_frames(owner: np.ndarray) -> np.ndarray:
    """The first, middle and last frame each chunk kept (a revisit may meet a chunk at either end)."""
    keys = []
    for c in range(int(owner.max()) + 1):
        own = np.flatnonzero(owner == c)
        keys += sorted({int(own[0]), int(own[len(own) // 2]), int(own[-1])})
    return np.array(keys)


def _revisits(prediction: Prediction, owner: np.ndarray, keys: np.ndarray, options: LoopOptions) -> tuple[int, list]:
    """``(candidates, [(overlap, chunk_a, chunk_b, key_a, key_b)])``: chunk pairs at least ``min_chunk_gap``
    calls apart whose key frames overlap (the best key pair of each), the farthest apart first, no two within
    ``min_chunk_gap`` of each other at both ends. ``keys``: :func:`_key_frames` of ``owner``."""
    overlap = overlap_matrix(prediction.subset(keys.tolist()))
    both = np.minimum(overlap, overlap.T)
    best: dict[tuple[int, int], tuple[float, int, int, int, int]] = {}
    for i, j in zip(*np.nonzero(both >= options.min_overlap)):
        a, b = int(owner[keys[i]]), int(owner[keys[j]])
        if b - a >= options.min_chunk_gap and both[i, j] > best.get((a, b), (0.0,))[0]:
            best[(a, b)] = (float(both[i, j]), a, b, int(keys[i]), int(keys[j]))
    chosen: list[tuple[float, int, int, int, int]] = []
    gap = options.min_chunk_gap
    # The longest revisits first: a loop closes the drift of the links it spans, and on a slow video chunks a few
    # calls apart overlap more than the far ends of a loop do.
    for loop in sorted(best.values(), key=lambda c: (c[2] - c[1], c[0]), reverse=True):
        a, b = loop[1:3]
        if len(chosen) < options.max_loops and all(abs(a - c[1]) >= gap or abs(b - c[2]) >= gap for c in chosen):
            chosen.append(loop)
    return len(best), chosen


def _end_frames(owner: np.ndarray, chunk: int, key: int, count: int) -> list[int]:
    """Up to ``count`` frames of ``chunk``, the nearest its key frame first, in capture order."""
    frames = np.flatnonzero(owner == chunk)
    return sorted(frames[np.argsort(np.abs(frames - key), kind="stable")[:count]].tolist())


def close_loops(
    prediction: Prediction,
    chunks: Sequence[Sequence[int]],
    run_calls: Callable[[list[list[int]]], Sequence[Prediction]],
    fit: Callable[[Prediction, Sequence[int], Prediction, Sequence[int]], tuple[Sim3, float]],
    options: LoopOptions = LoopOptions(),
) -> tuple[Prediction, LoopClosure | None]:
    """The merged ``prediction`` with its chunks moved by the pose graph over the loops found (unchanged
    without any), and what was done (None when the pass did not run: off, or too few chunks for a loop).

    ``run_calls`` runs model calls on lists of frame indices (decoded, validated); ``fit`` gives the Sim(3)
    ``ref_from_new`` of a call's frames onto the chain and its misfit (median point distance / depth). A loop
    call the model fails on (a :class:`ModelError`) leaves the chunks as merged, with a warning and the
    error in the report: the chunks themselves were good.
    """
    owner = owners(chunks, len(prediction))
    if not options.enabled or options.max_loops == 0 or len(chunks) <= options.min_chunk_gap:
        return prediction, None
    keys = _key_frames(owner)
    candidates, chosen = _revisits(prediction, owner, keys, options)
    if not chosen:
        log.info("loop chunks: no revisit among %d chunks", len(chunks))
        return prediction, LoopClosure(0, ())
    try:
        calls = _measured(prediction, owner, chunks, chosen, run_calls, fit, options)
    except ModelError as error:
        log.warning("loop chunks: a loop call failed, the chunks stay as merged: %s", error.problem)
        return prediction, LoopClosure(candidates, (), error=error.problem)
    used = [c for c in calls if c.used]
    if not used:
        log.warning("loop chunks: all %d loop calls left out (they did not fit the chain)", len(calls))
        return prediction, LoopClosure(candidates, calls)
    edges = [Sim3Edge(c, c + 1, Sim3.identity()) for c in range(len(chunks) - 1)]
    edges += [Sim3Edge(*c.chunks, c.b_from_a) for c in used]
    medians = [np.median(d[d > 0]) for d in (prediction.depth[k] for k in keys) if (d > 0).any()]
    length = float(np.median(medians)) if medians else 1.0
    graph = optimize_pose_graph([Sim3.identity()] * len(chunks), edges, length, options.pose_graph)
    if not all(np.isfinite(c.matrix()).all() for c in graph.world_from_node):
        log.warning("loop chunks: the pose graph gave no finite corrections; the chunks stay as merged")
        return prediction, LoopClosure(candidates, calls, graph.iterations, error="no finite pose-graph solution")
    turns = rotation_angle_deg(np.stack([c.rotation for c in graph.world_from_node]))
    scales = np.abs(np.log([c.scale for c in graph.world_from_node]))
    log.info(
        "loop chunks: %d of %d loop calls closed the chain (missed by up to %.2f deg); chunks moved up to %.2f deg",
        len(used),
        len(calls),
        max(c.closure_deg for c in used),
        turns.max(),
    )
    summary = LoopClosure(candidates, calls, graph.iterations, float(turns.max()), float(np.exp(scales.max())))
    return _corrected(prediction, owner, graph.world_from_node), summary


def _measured(prediction, owner, chunks, chosen, run_calls, fit, options: LoopOptions) -> tuple[LoopCall, ...]:
    """One model call per chosen revisit, each end fitted onto the chain: the loop calls, used or not."""
    per_end = max(min(options.frames_per_end, len(chunks[0]) // 2), 1)
    ends = [(_end_frames(owner, a, ka, per_end), _end_frames(owner, b, kb, per_end)) for _, a, b, ka, kb in chosen]
    parts = run_calls([first + second for first, second in ends])
    calls = []
    for (value, a, b, _, _), (first, second), part in zip(chosen, ends, parts):
        fit_a, misfit_a = fit(prediction, first, part, range(len(first)))
        fit_b, misfit_b = fit(prediction, second, part, range(len(first), len(first) + len(second)))
        b_from_a = fit_b.compose(fit_a.inverse())  # what the chain's b-end should be, seen from its a-end
        closure = float(rotation_angle_deg(b_from_a.rotation[None])[0])
        used = max(misfit_a, misfit_b) <= options.max_misfit and closure <= options.max_closure_deg
        frames = tuple(first + second)
        calls.append(LoopCall(frames, (a, b), value, (misfit_a, misfit_b), closure, b_from_a.scale, used, b_from_a))
    return tuple(calls)


def _corrected(prediction: Prediction, owner: np.ndarray, corrections: Sequence[Sim3]) -> Prediction:
    """Every frame moved by its chunk's correction (``corrected_from_merged``): pose and depth scale."""
    poses = np.stack([corrections[c].transform_cam_from_world(p) for c, p in zip(owner, prediction.cam_from_world)])
    depth = tuple(d * np.float32(corrections[c].scale) for c, d in zip(owner, prediction.depth))
    return dataclasses.replace(prediction, cam_from_world=poses, depth=depth)
