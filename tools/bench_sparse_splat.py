"""Held-out PSNR of the splat on a sparse, wide-baseline capture: photometric pose refinement and the model's
depth as a prior, each off and on, from the model's cameras and from the refined ones.

Usage (from the repository root):

    .venv/bin/python tools/bench_sparse_splat.py                    # 8 views, 20 s per splat, weight 0.2
    .venv/bin/python tools/bench_sparse_splat.py --seconds 60 --depth-weight 0.5 --bad-frame 3

The scene is ffrecon's wide-baseline synthetic one (8 views 30-60 deg apart at 320x240, plain walls; plain
COLMAP registers 3 of 8). The model is simulated: true cameras and depth with 2.5 deg / 3 % errors
(``--bad-frame k``: frame k 25 deg off too), in the true world frame. Every 4th frame (0 and 4) is held
out. The held-out views are rendered at their **true** cameras, so that the score measures the splat
(and the training cameras it was fitted with), not the error of a held-out camera nothing refines; the
first training view, which fixes the splat's frame (the gauge, as VGGT's first frame fixes its world),
gets its true camera too.
"Pose refinement" optimises every training camera but one with the Gaussians (the pipeline does so
only for frames no evidence confirmed); the printed rotation error is the training cameras' median
against the truth after the splat. Each splat gets the same time budget on one thread.
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ffrecon.geometry.metrics import pose_errors
from ffrecon.sfm.refine.options import RefineInputs, RefineOptions
from ffrecon.sfm.refine.run import run_refine
from ffrecon.splat.optimize import OptimizeOptions
from ffrecon.splat.stage import SplatOptions, run_splat_from_prediction, split_views
from ffrecon.synthetic import CameraPath, SceneOptions, Texture, make_scene, write_scene
from ffrecon.synthetic.simulated_model import SimulationOptions, prediction_from_truth, simulate

WIDE = SceneOptions(num_frames=8, width=320, height=240, path=CameraPath.WIDE, texture=Texture.PLAIN_WALLS, seed=3)


def _splat(scene, pred, cams, *, refine_poses: bool, depth_weight: float, seconds: float, out: Path):
    options = SplatOptions(
        holdout_every=4,
        video=False,
        spz=False,
        curve_every=0,
        depth_prior_below=100 if depth_weight > 0 else 0,
        optimize=OptimizeOptions.brief(max_seconds=seconds, depth_weight=depth_weight, threads=1, progress=False),
    )
    train, heldout = split_views(len(scene), options.holdout_every)
    poses = cams.copy()
    # Scored at the true cameras, in the frame of the first training view's true camera, which no splat moves
    # (the gauge; VGGT's world is its first frame's camera): see the module docstring.
    poses[heldout + train[:1]] = scene.cam_from_world[heldout + train[:1]]
    unconfirmed = train if refine_poses or depth_weight > 0 else ()  # the stage's depth prior needs one
    if not refine_poses:
        options = replace(options, refine_unconfirmed_poses=False)
    result = run_splat_from_prediction(
        pred, list(scene.images), poses, pred.cameras, options, out, unconfirmed=unconfirmed
    )
    errors = pose_errors(result.cam_from_world[train], scene.cam_from_world[train]).per_image_rotation_deg
    return result, float(np.median(errors))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=20.0, help="optimisation budget per splat")
    parser.add_argument("--depth-weight", type=float, default=0.2)
    parser.add_argument("--bad-frame", type=int, default=None, help="also put this frame 25 deg off")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    scene = make_scene(WIDE)
    sim = SimulationOptions(seed=3, bad_frames=() if args.bad_frame is None else (args.bad_frame,), bad_rotation_deg=25)
    truth, _ = simulate(scene, sim)
    pred = prediction_from_truth(scene, truth, sim)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        refined = run_refine(RefineInputs(write_scene(scene, tmp / "scene")), pred, RefineOptions(), tmp / "refine")
        sets = {"model": pred.cam_from_world, "refined": refined.cam_from_world}
        print(f"wide scene, 8 views {WIDE.width}x{WIDE.height}, {args.seconds:.0f} s per splat, 1 thread")
        print("cameras  pose-refine  depth-prior  held-out PSNR dB  SSIM   train rot. err. deg  seconds")
        for label, cams in sets.items():
            before = float(np.median(pose_errors(cams, scene.cam_from_world).per_image_rotation_deg))
            print(f"{label:8s} (median rotation error before the splat: {before:.2f} deg)")
            for refine_poses in (False, True):
                for weight in (0.0, args.depth_weight):
                    start = time.perf_counter()
                    out = tmp / f"{label}-{refine_poses}-{weight}"
                    res, err = _splat(
                        scene, pred, cams, refine_poses=refine_poses, depth_weight=weight, seconds=args.seconds, out=out
                    )
                    print(
                        f"{label:8s} {'on' if refine_poses else 'off':11s}  {weight:<11.2g}  "
                        f"{res.mean('psnr_optimized'):16.2f}  {res.mean('ssim_optimized'):.3f}  {err:19.2f}  "
                        f"{time.perf_counter() - start:7.1f}"
                    )


if __name__ == "__main__":
    main()
