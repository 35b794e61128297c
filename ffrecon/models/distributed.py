"""Feed-forward chunks on Ray: the same model calls, run by Ray's workers on this machine or on a cluster.

A multi-view model's chunks are independent until they are merged (:func:`~ffrecon.models.multiview.
merge_chunks` fits the Sim(3) on shared frames), so each chunk is one call to a Ray actor that holds its
own onnxruntime session, and the parts come back in chunk order to be merged exactly as the local loop
merges them. Ray places the actors and moves the frames (its object store); ffrecon schedules nothing
itself. ``ray.init()`` with no address starts a local instance (the CPUs of this machine); an address
(``auto``, or ``ray://HEAD:10001``) joins a running cluster, whose workers must have ffrecon installed and
the model file at the same path (a shared file system, or the same copy on every node): docs/pipeline.md.

Ray is an optional dependency (``pip install 'ffrecon[distributed]'``), imported only here and only when
asked for.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from ffrecon.checks import check_number
from ffrecon.errors import FFReconError, InputError, ModelError
from ffrecon.models.adapters import PreprocessMode, adapter_for
from ffrecon.models.multiview import ChunkLayout, MultiviewOptions, chunking, predict_chunk
from ffrecon.models.runner import OnnxModel
from ffrecon.types import ModelInfo, Prediction

log = logging.getLogger("ffrecon.models")

INSTALL_FIX = "pip install 'ffrecon[distributed]' (Ray), or run without --ray"
WORKER_FIX = "read the workers' logs (`ray logs`); out of memory: a smaller --chunk-size, or fewer --ray-workers"


@dataclass(frozen=True, kw_only=True)
class RayOptions:
    address: str | None = None  # None: start a local Ray instance; "auto" or "ray://HEAD:10001": join a cluster
    workers: int | None = None  # model sessions (actors); None: as many as Ray's CPUs (GPUs) allow, at most one a chunk
    cpus_per_worker: int = 1  # Ray CPUs per actor, and its onnxruntime threads
    gpus_per_worker: float = 0.0  # 1 on a GPU cluster: each actor gets a GPU (onnxruntime's CUDA provider)
    wait_seconds: float = 3600.0  # longest wait for the next chunk to finish before the run stops (no hang)

    def __post_init__(self) -> None:
        check_number("RayOptions.wait_seconds", self.wait_seconds, low=0, low_open=True)
        check_number("RayOptions.workers", self.workers, low=1, integer=True, allow_none=True, flag="--ray-workers")
        check_number("RayOptions.cpus_per_worker", self.cpus_per_worker, low=1, integer=True)
        check_number("RayOptions.gpus_per_worker", self.gpus_per_worker, low=0, flag="--ray-gpus")


@dataclass(frozen=True)
class RayParts:
    parts: tuple[Prediction, ...]  # each chunk's prediction, in chunk order
    layout: ChunkLayout


class ChunkWorker:
    """One onnxruntime session on a Ray worker; :meth:`predict` runs one chunk (as the local loop would)."""

    def __init__(self, model_path: str, threads: int, use_cuda: bool) -> None:
        import os
        import socket

        self.model = OnnxModel(model_path, threads=threads, use_cuda=use_cuda)
        self.where = f"{socket.gethostname()}:{os.getpid()}"

    def predict(
        self,
        images: list[np.ndarray],
        names: list[str],
        info: ModelInfo,
        mode: PreprocessMode,
        options: MultiviewOptions,
    ) -> tuple[Prediction, str]:
        """One chunk's prediction, decoded with the driver's ``info`` (so that parts merge as the local
        loop's do), and where it ran."""
        adapter = adapter_for(self.model.family)
        infer = lambda batch: self.model.run_checked(adapter.input_name, {adapter.input_name: batch})  # noqa: E731
        return predict_chunk(images, names, infer, info, mode, adapter, options), self.where


def _ray():
    try:
        import ray
    except ImportError as exc:
        raise InputError("--ray needs Ray, which is not installed", INSTALL_FIX) from exc
    return ray


def _connect(ray, options: RayOptions) -> bool:
    """Start or join Ray; True when this call started it (and so shuts it down after)."""
    if ray.is_initialized():
        return False
    try:
        ray.init(address=options.address, include_dashboard=False, log_to_driver=False, logging_level=logging.WARNING)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        raise InputError(
            f"cannot start or join Ray at {options.address or 'a new local instance'}: {str(exc).splitlines()[0]}",
            "check the address (`ray status` on the head node), or leave --ray's address out to run locally",
        ) from exc
    return True


def _worker_count(ray, options: RayOptions, num_chunks: int) -> int:
    """Actors to start: as asked, else as many as the cluster's resources hold (one a chunk at most). An
    :class:`InputError` when not even one fits (Ray would wait for it for ever)."""
    resources = ray.cluster_resources()
    by_cpu = int(resources.get("CPU", 0) // options.cpus_per_worker)
    by_gpu = int(resources.get("GPU", 0) // options.gpus_per_worker) if options.gpus_per_worker else by_cpu
    if min(by_cpu, by_gpu) < 1:
        raise InputError(
            f"the Ray cluster has {resources.get('CPU', 0):g} CPUs and {resources.get('GPU', 0):g} GPUs: not enough "
            f"for one model session ({options.cpus_per_worker} CPUs, {options.gpus_per_worker:g} GPUs)",
            "add nodes with GPUs to the cluster, or leave --ray-gpus out to run the sessions on CPUs",
        )
    return min(options.workers or min(by_cpu, by_gpu), num_chunks)


def predict_chunks_ray(
    model: ModelInfo,
    images: Sequence[np.ndarray],
    names: Sequence[str],
    chunks: Sequence[Sequence[int]],
    mode: PreprocessMode,
    multiview: MultiviewOptions,
    options: RayOptions,
) -> RayParts:
    """Each chunk's decoded, validated prediction (in chunk order), run by Ray actors, and where they ran.

    ``multiview`` holds the resolved chunk size and overlap that made ``chunks``."""
    ray = _ray()
    started = _connect(ray, options)
    try:
        count = _worker_count(ray, options, len(chunks))
        actor = ray.remote(num_cpus=options.cpus_per_worker, num_gpus=options.gpus_per_worker)(ChunkWorker)
        use_cuda = options.gpus_per_worker > 0
        path = str(Path(model.path).resolve())
        actors = [actor.remote(path, options.cpus_per_worker, use_cuda) for _ in range(count)]
        log.info("feed-forward: %d chunks on %d Ray workers", len(chunks), count)
        futures = [
            actors[i % count].predict.remote(
                [images[k] for k in chunk], [names[k] for k in chunk], model, mode, multiview
            )
            for i, chunk in enumerate(chunks)
        ]
        results = _gather(ray, futures, options.wait_seconds)
        where = tuple(w for _, w in results)
        address = "local" if started and options.address is None else str(options.address or "connected")
        engine = dict(engine="ray", address=address, workers=count, nodes=len({w.split(":")[0] for w in where}))
        layout = ChunkLayout.of(chunks, *chunking(multiview), chunk_workers=where, **engine)
        return RayParts(tuple(part for part, _ in results), layout)
    finally:
        if started:
            ray.shutdown()


def _gather(ray, futures: list, wait_seconds: float) -> list:
    """The futures' values in order, with a progress bar as they finish. A worker's ffrecon error is raised
    as itself (Ray wraps it in a RayTaskError); a dead worker, or no chunk finishing within
    ``wait_seconds``, is a :class:`ModelError`."""
    pending = list(futures)
    with tqdm(total=len(futures), desc="feed-forward (ray)", unit="chunk", disable=None) as bar:
        while pending:
            done, pending = ray.wait(pending, num_returns=1, timeout=wait_seconds)
            if not done:
                raise ModelError(
                    f"no chunk finished on Ray within {wait_seconds:g} s ({len(pending)} of {len(futures)} left)",
                    "check `ray status` (workers waiting for resources?) and the workers' logs (`ray logs`)",
                )
            bar.update(len(done))
    try:
        return ray.get(futures)
    except ray.exceptions.RayTaskError as exc:
        if isinstance(getattr(exc, "cause", None), FFReconError):
            raise exc.cause from None
        raise ModelError(f"a Ray worker failed: {str(exc).splitlines()[0]}", WORKER_FIX) from exc
    except ray.exceptions.RayError as exc:  # a worker that died (out of memory, node lost)
        raise ModelError(f"a Ray worker was lost: {str(exc).splitlines()[0]}", WORKER_FIX) from exc
