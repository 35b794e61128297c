"""Benchmark: which pairs COLMAP's cross-check matches on a long capture, and which mapper builds the model.

On one synthetic orbit of ``--frames`` frames (one full loop around the room, so the last frames revisit
the first) with its simulated model (``depth_stride`` 4), each row runs ``run_colmap``, the cross-check's
own code, on the same images:

- ``exhaustive``: every pair (COLMAP alone, the reference);
- ``model``: the pairs the model's cameras and depth say overlap (``--pairing model``; ``geometry/overlap.py``);
- ``sequential``: COLMAP's sequential pairing alone (the next 10 frames and those 2^k ahead);
- ``sequential+retrieval``: the same plus ffrecon's loop candidates (VLAD over SIFT, ``sfm/crosscheck/retrieval.py``).

Then the incremental and the global mapper each map the ``model`` row's database (mapping time only).
Printed per row: seconds per step, pairs matched and verified, registered frames, AUC@5 and median
rotation error against the truth, ATE after a Sim(3), and the loop gap error (the first and last frames'
distance, estimated against true, after the Sim(3); a path that drifts opens a gap at the loop).

Usage (from the repository root)::

    .venv/bin/python tools/bench_pairing.py --frames 120
    .venv/bin/python tools/bench_pairing.py --frames 400 --rows model sequential+retrieval --mappers

Timings on a shared machine are pessimistic; rerun the rows you compare in one invocation.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from ffrecon.colmap_io import cam_from_world_by_name
from ffrecon.geometry.alignment import umeyama
from ffrecon.geometry.metrics import pose_errors
from ffrecon.geometry.overlap import overlap_graph
from ffrecon.geometry.poses import camera_centers
from ffrecon.models.multiview import MultiviewOptions, predict_multiview
from ffrecon.models.runner import MULTIVIEW_INPUT, OnnxModel
from ffrecon.sfm.crosscheck.mapping import map_images
from ffrecon.sfm.crosscheck.options import ColmapOptions, MapperKind, PairingMode
from ffrecon.sfm.crosscheck.retrieval import RetrievalOptions
from ffrecon.sfm.crosscheck.run import run_colmap
from ffrecon.sfm.features import colmap_log_level
from ffrecon.synthetic import SceneOptions, make_scene
from ffrecon.synthetic.scene import write_scene
from ffrecon.synthetic.simulated_model import SimulationOptions, build_simulated_vggt

ROWS = {
    "exhaustive": ColmapOptions(pairing=PairingMode.EXHAUSTIVE, mapper=MapperKind.INCREMENTAL),
    "model": ColmapOptions(pairing=PairingMode.MODEL, mapper=MapperKind.INCREMENTAL),
    "sequential": ColmapOptions(
        pairing=PairingMode.SEQUENTIAL, mapper=MapperKind.INCREMENTAL, retrieval=RetrievalOptions(enabled=False)
    ),
    "sequential+retrieval": ColmapOptions(pairing=PairingMode.SEQUENTIAL, mapper=MapperKind.INCREMENTAL),
}


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--seed", type=int, default=2)
    parser.add_argument("--rows", nargs="+", choices=list(ROWS), default=list(ROWS))
    parser.add_argument("--mappers", action="store_true", help="also map the model row's database with each mapper")
    parser.add_argument("--max-mapping-seconds", type=int, default=3600)
    parser.add_argument("--out", type=Path, default=None, help="work folder (default: a temporary one, removed)")
    parser.add_argument("--json", type=Path, default=None, help="also save the rows here")
    return parser


def _accuracy(cam_from_world: np.ndarray, registered: np.ndarray, truth: np.ndarray) -> dict:
    errors = pose_errors(cam_from_world[registered], truth[registered])
    est, ref = camera_centers(cam_from_world[registered]), camera_centers(truth[registered])
    aligned = umeyama(est, ref).apply(est)
    gap = abs(np.linalg.norm(aligned[0] - aligned[-1]) - np.linalg.norm(ref[0] - ref[-1]))
    return {
        "registered": int(registered.sum()),
        "auc5": round(float(errors.auc[5]), 4),
        "median_rotation_deg": round(float(np.median(errors.per_image_rotation_deg)), 4),
        "ate": round(float(np.sqrt(np.mean(np.sum((aligned - ref) ** 2, axis=1)))), 5),
        "loop_gap_error": round(float(gap), 5),
    }


def _model_pairs(scene, model_path: Path) -> tuple[list[tuple[str, str]], dict]:
    model = OnnxModel(model_path)
    start = time.perf_counter()
    infer = lambda batch: model.run({MULTIVIEW_INPUT: batch})  # noqa: E731
    names = list(scene.names)
    prediction = predict_multiview(list(scene.images), names, infer, model.info(), MultiviewOptions(chunk_size=24))
    inference = time.perf_counter() - start
    start = time.perf_counter()
    pairs = overlap_graph(prediction).pairs
    seconds = {"inference": round(inference, 1), "overlap_graph": round(time.perf_counter() - start, 2)}
    return [(names[i], names[j]) for i, j in pairs], seconds


def _mapper_rows(root: Path, images: Path, scene, max_seconds: int) -> list[dict]:
    rows = []
    for kind in (MapperKind.INCREMENTAL, MapperKind.GLOBAL):
        work = root / f"mapper_{kind.value}"
        work.mkdir()
        shutil.copy(root / "model" / "database.db", work / "database.db")
        start = time.perf_counter()
        with colmap_log_level():
            options = ColmapOptions(mapper=kind, max_mapping_seconds=max_seconds)
            best, _, _ = map_images(work / "database.db", images, work / "mapper", options, len(scene.names))
        seconds = round(time.perf_counter() - start, 1)
        poses, registered = cam_from_world_by_name(best, scene.names)
        rows.append(
            {"row": f"{kind.value} mapper", "mapping_s": seconds, **_accuracy(poses, registered, scene.cam_from_world)}
        )
        print(json.dumps(rows[-1]), flush=True)
    return rows


def main() -> None:
    args = _parser().parse_args()
    root = args.out or Path(tempfile.mkdtemp(prefix="bench_pairing_"))
    scene = make_scene(SceneOptions(num_frames=args.frames, width=args.width, height=args.height, seed=args.seed))
    images = write_scene(scene, root / "scene")
    build_simulated_vggt(scene, root / "sim.onnx", SimulationOptions(seed=args.seed, depth_stride=4))
    pairs, model_seconds = _model_pairs(scene, root / "sim.onnx")
    print(
        json.dumps(
            {
                "frames": args.frames,
                "model_pairs": len(pairs),
                "all_pairs": args.frames * (args.frames - 1) // 2,
                **model_seconds,
            }
        )
    )
    rows = []
    for name in args.rows:
        options = dataclasses.replace(ROWS[name], max_mapping_seconds=args.max_mapping_seconds)
        start = time.perf_counter()
        result = run_colmap(
            images,
            scene.names,
            options,
            root / name,
            focal_prior_px=None,
            model_pairs=pairs if name == "model" else None,
        )
        row = {"row": name, "seconds": round(time.perf_counter() - start, 1), **result.timings.to_report()}
        row |= {
            "pairs_matched": result.features.num_pairs_matched,
            "pairs_verified": result.features.num_pairs_verified,
        }
        row |= {"loop_candidates": result.features.num_loop_candidates}
        rows.append(row | _accuracy(result.cam_from_world, result.registered, scene.cam_from_world))
        print(json.dumps(rows[-1]), flush=True)
    if args.mappers and "model" in args.rows:
        rows += _mapper_rows(root, images, scene, args.max_mapping_seconds)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    if args.out is None:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
