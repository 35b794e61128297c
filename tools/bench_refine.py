"""Benchmark: ffrecon's feed-forward-seeded refinement against plain COLMAP, on synthetic orbits.

For each frame count, one synthetic scene is rendered and the simulated model's errors are drawn
(2.5 deg rotation, 3% centre and focal error). Then, each in a fresh subprocess (so that peak memory
is per method):

- refine:  ffrecon.sfm.refine.run.run_refine with its own SIFT extraction (model inference excluded);
- refine*: the same reusing the cross-check's SIFT features, as the pipeline does;
- colmap:  SIFT extraction, exhaustive matching, incremental mapping (ffrecon.sfm.crosscheck.run.run_colmap,
           given the same feed-forward focal prior).

Accuracy is against ground truth. Usage::

    python tools/bench_refine.py                       # 12 24 48 96 frames, rich texture
    python tools/bench_refine.py --frames 24 --texture repeated
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ffrecon.geometry.metrics import pose_errors
from ffrecon.sfm.crosscheck.options import ColmapOptions
from ffrecon.sfm.crosscheck.run import run_colmap
from ffrecon.sfm.refine.options import RefineInputs, RefineOptions
from ffrecon.sfm.refine.run import run_refine
from ffrecon.synthetic import SceneOptions, Texture, load_scene, make_scene, write_scene
from ffrecon.synthetic.simulated_model import SimulationOptions, prediction_from_truth, simulate
from ffrecon.types import ModelFamily, ModelInfo, PinholeCamera, Prediction


def _prediction(scene_dir: Path) -> Prediction:
    scene = load_scene(scene_dir)
    with np.load(scene_dir / "prediction.npz") as data:
        cameras = tuple(PinholeCamera.from_K(K, scene.camera.width, scene.camera.height) for K in data["K"])
        return Prediction(
            scene.names,
            data["cam_from_world"],
            cameras,
            tuple(data["depth"]),
            tuple(data["conf"]),
            ModelInfo("simulated", ModelFamily.MULTIVIEW, simulated=True),
        )


def prepare(scene_dir: Path, frames: int, texture: Texture, seed: int) -> None:
    """Render the scene and store the simulated model's output at original resolution."""
    scene = make_scene(SceneOptions(num_frames=frames, texture=texture, seed=seed))
    write_scene(scene, scene_dir)
    sim = SimulationOptions(seed=seed)
    truth, _ = simulate(scene, sim)
    pred = prediction_from_truth(scene, truth, sim)
    np.savez(
        scene_dir / "prediction.npz",
        cam_from_world=truth.cam_from_world,
        K=truth.K,
        depth=truth.depth,
        conf=np.stack(pred.depth_conf),
    )


def child(method: str, scene_dir: Path, out_dir: Path) -> dict:
    """Run one method and return its measurements (runs in its own process)."""
    scene = load_scene(scene_dir)
    prediction = _prediction(scene_dir)
    start = time.perf_counter()
    if method == "colmap":
        result = run_colmap(
            scene_dir / "images",
            scene.names,
            ColmapOptions(),
            out_dir / "colmap",
            focal_prior_px=[c.fx for c in prediction.cameras],
        )
        stages = result.timings.to_report()
    else:
        reuse = out_dir / "colmap" / "database.db" if method == "refine_reuse" else None
        result = run_refine(
            RefineInputs(scene_dir / "images", reuse_features_from=reuse), prediction, RefineOptions(), out_dir / method
        )
        stages = result.timings.to_report()
    wall = time.perf_counter() - start
    errors = pose_errors(result.cam_from_world, scene.cam_from_world, result.registered)
    return {
        "method": method,
        "wall_s": wall,
        "stages": stages,
        "registered": int(result.registered.sum()),
        "auc5": errors.auc[5],
        "auc30": errors.auc[30],
        "ate_rel": errors.ate_relative,
        "med_rot": errors.median_rotation_deg,
        "peak_mb": _peak_rss_mb(),
    }


def _peak_rss_mb() -> float:
    """High-water mark of this process's resident memory (VmHWM; ru_maxrss survives exec on Linux)."""
    status = Path("/proc/self/status")
    if status.is_file():
        for line in status.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) / 1024.0
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _run_child(method: str, scene_dir: Path, out_dir: Path) -> dict:
    cmd = [sys.executable, __file__, "--child", method, "--scene", str(scene_dir), "--out", str(out_dir)]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _stage(row: dict, *names: str) -> float:
    return sum(row["stages"].get(n, 0.0) for n in names)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, nargs="+", default=[12, 24, 48, 96])
    parser.add_argument("--texture", choices=[t.value for t in Texture], default="rich")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--child", choices=["refine", "refine_reuse", "colmap"], help=argparse.SUPPRESS)
    parser.add_argument("--scene", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args.child, args.scene, args.out)))
        return
    header = (
        f"{'N':>4} {'method':<8} {'pairs/extr':>10} {'match':>7} {'map/BA':>7} {'total':>7} {'ratio':>6} "
        f"{'reg':>4} {'AUC@5':>6} {'AUC@30':>6} {'ATE%':>6} {'medrot':>7} {'peakMB':>7}"
    )
    print(f"texture={args.texture}; times in seconds; ratio = COLMAP total / method total; ATE% of the camera extent")
    print(header)
    with tempfile.TemporaryDirectory(prefix="ffrecon-bench-") as tmp:
        for frames in args.frames:
            scene_dir = Path(tmp) / f"scene{frames}"
            prepare(scene_dir, frames, Texture(args.texture), args.seed)
            out = Path(tmp) / f"out{frames}"
            rows = [_run_child(m, scene_dir, out) for m in ("refine", "colmap", "refine_reuse")]
            colmap_total = rows[1]["stages"]["total"]
            for row in rows:
                label = {"refine": "refine", "colmap": "colmap", "refine_reuse": "refine*"}[row["method"]]
                first = _stage(row, "pair_selection", "feature_extraction")
                last = _stage(row, "mapping", "triangulation_and_bundle_adjustment", "export")
                total = row["stages"]["total"]
                print(
                    f"{frames:>4} {label:<8} {first:>10.2f} {_stage(row, 'matching'):>7.2f} {last:>7.2f} {total:>7.2f} "
                    f"{colmap_total / total:>6.2f} {row['registered']:>4} {row['auc5']:>6.3f} {row['auc30']:>6.3f} "
                    f"{100 * row['ate_rel']:>6.3f} {row['med_rot']:>7.3f} {row['peak_mb']:>7.0f}",
                    flush=True,
                )
    print("refine* reuses the cross-check's SIFT features (as the pipeline does); refine extracts its own.")


if __name__ == "__main__":
    main()
