"""Benchmark: one bundle adjustment of a long capture, the whole problem against thinned tracks first.

Reads a refined COLMAP model (``OUT/refine/model`` of an ``ffrecon run``, e.g. the 500-frame bench scene's),
moves every camera centre by a random offset (``--offset``, model units; seed 0), and adjusts it with the
refinement's own adjuster (``ffrecon.sfm.refine.bundle._Adjuster``, one thread, no priors, trivial loss, run to
convergence) three times, each on a fresh copy:

- ``whole``: ``BundleOptions(thin_from_images=0)``, Ceres' sparse Schur solver on every observation;
- ``thinned``: the default from 200 frames: tracks thinned to ``max_track_images`` first, then the whole
  problem from there with the iterative Schur solver to a 1e-6 relative change;
- ``thinned, all cores``: the same with every core (not faster here: the refinement keeps one thread).

Printed per row: seconds, final cost, and the largest rotation difference between the two results' cameras
(degrees). On a dense video a point is seen by more frames the more frames there are; the whole problem's
cost then grows much faster than its observations (docs/pipeline.md, "Long captures").

Usage (from the repository root)::

    .venv/bin/python tools/bench_bundle.py OUT/refine/model
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
import pycolmap

from ffrecon.geometry.rotations import rotation_angle_deg
from ffrecon.sfm.refine.bundle import BundleOptions, _Adjuster


def moved(rec: pycolmap.Reconstruction, offset: float) -> pycolmap.Reconstruction:
    """A copy of ``rec`` with every registered camera centre moved by ``offset`` (normal, per axis)."""
    out = pycolmap.Reconstruction(rec)
    rng = np.random.default_rng(0)
    for image_id in sorted(out.reg_image_ids()):
        image = out.image(image_id)
        pose = image.cam_from_world()
        translation = np.asarray(pose.translation) + rng.normal(0, offset, 3)
        out.frame(image.frame_id).rig_from_world = pycolmap.Rigid3d(pose.rotation, translation)
    return out


def adjusted(rec: pycolmap.Reconstruction, options: BundleOptions) -> tuple[float, float]:
    """Adjust ``rec`` in place: ``(seconds, final cost)``."""
    adjust = _Adjuster(options, None, 0.0)
    start = time.perf_counter()
    adjust(rec, pycolmap.LossFunctionType.TRIVIAL)
    return time.perf_counter() - start, float(adjust.last.ceres_summary.final_cost) if adjust.last else float("nan")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", type=Path, help="a COLMAP model folder (cameras, images, points3D)")
    parser.add_argument("--offset", type=float, default=0.01, help="camera centre noise, model units")
    parser.add_argument("--max-track-images", type=int, default=BundleOptions().max_track_images)
    args = parser.parse_args(argv)
    rec = pycolmap.Reconstruction(args.model)
    lengths = np.array([p.track.length() for p in rec.points3D.values()])
    print(f"{rec.num_reg_images()} frames, {len(lengths)} points, track length mean {lengths.mean():.1f}")
    rows = {
        "whole": BundleOptions(thin_from_images=0, num_threads=1),
        "thinned": BundleOptions(thin_from_images=1, max_track_images=args.max_track_images, num_threads=1),
        # measured on the 500-frame bench model, 2 cores: 18.1 s against 14.5 s on one (so the refinement keeps one)
        "thinned, all cores": BundleOptions(
            thin_from_images=1, max_track_images=args.max_track_images, num_threads=os.cpu_count() or 1
        ),
    }
    results = {}
    for name, options in rows.items():
        results[name] = moved(rec, args.offset)
        seconds, cost = adjusted(results[name], options)
        print(f"{name:<18} {seconds:7.1f} s  final cost {cost:.1f}")
    ids = sorted(rec.reg_image_ids())
    rotations = [[results[n].image(i).cam_from_world().rotation.matrix() for i in ids] for n in rows]
    for other in range(1, len(rows)):
        apart = max(rotation_angle_deg(a @ b.T) for a, b in zip(rotations[0], rotations[other]))
        print(f"largest rotation difference, whole vs {list(rows)[other]}: {apart:.4f} deg")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
