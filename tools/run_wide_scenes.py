"""Issue 21's acceptance, end to end, on held-out seeds of the wide-baseline scene: ``ffrecon run`` as a
user runs it, default and ``--quick``, one process per run.

Usage (from the repository root):

    .venv/bin/python tools/run_wide_scenes.py --seeds 25 46          # no frame off
    .venv/bin/python tools/run_wide_scenes.py --seeds 13 --bad-frame 5

The scene is ffrecon's wide-baseline synthetic one (8 views 30-60 deg apart at 320x240, plain walls;
plain COLMAP registers under half), the model the simulated VGGT (2.5 deg / 3 % errors; ``--bad-frame k``:
frame k 25 deg off too) exported to ONNX. Per run it prints the exit code, whether ``splat.ply`` was
written, how many frames ``sparse/0`` holds, the median rotation error of its cameras against the truth
(after the best common rotation) and the largest of a frame called confirmed, and every frame's verdict
(C confirmed, X contradicted, ? unchecked), and the bad frame's error where sparse/0 holds it. The
acceptance: exit 0, a splat, every frame in sparse/0 with no frame off, median error at most 1 deg, no
confirmed frame over 5 deg, the bad frame never confirmed.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pycolmap

from ffrecon.geometry.metrics import aligned_rotation_errors_deg
from ffrecon.synthetic import CameraPath, SceneOptions, Texture, make_scene, write_scene
from ffrecon.synthetic.simulated_model import SimulationOptions, build_simulated_vggt

_LETTER = {"confirmed": "C", "contradicted": "X", "unchecked": "?"}


def _errors(out: Path, scene) -> tuple[list[str], np.ndarray]:
    """The frames of ``out/sparse/0`` and their rotation errors against the truth."""
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    names = sorted(im.name for im in rec.images.values() if im.has_pose)
    by_name = {im.name: im for im in rec.images.values()}
    poses = np.stack([by_name[n].cam_from_world().matrix()[:, :3] for n in names])
    truth = np.stack([scene.cam_from_world[scene.names.index(n)][:, :3] for n in names])
    return names, aligned_rotation_errors_deg(poses, truth)


def _run(scene, images: Path, model: Path, out: Path, quick: bool, splat_seconds: float, bad: tuple) -> str:
    args = [sys.executable, "-m", "ffrecon", "run", str(images), "--model", str(model), "-o", str(out), "-q"]
    args += ["--splat-seconds", str(splat_seconds)] + (["--quick"] if quick else [])
    start = time.perf_counter()
    code = subprocess.run(args, capture_output=True, text=True).returncode
    seconds = time.perf_counter() - start
    if not (out / "report.json").is_file() or not (out / "sparse" / "0").is_dir():
        return f"exit {code}, no report or sparse/0 ({seconds:.0f} s)"
    report = json.loads((out / "report.json").read_text())
    verdicts = {e["name"]: e["verdict"] for e in report["evidence"]["per_image"]}
    names, errors = _errors(out, scene)
    confirmed = [e for n, e in zip(names, errors) if verdicts.get(n) == "confirmed"]
    letters = "".join(_LETTER.get(verdicts.get(n, ""), "-") for n in scene.names)
    off = {scene.names[k]: round(float(errors[names.index(scene.names[k])]), 1) for k in bad if scene.names[k] in names}
    return (
        f"exit {code}, splat {(out / 'splat.ply').is_file()}, sparse/0 {len(names)}/{len(scene.names)}, "
        f"median error {np.median(errors):.2f} deg, max confirmed {max(confirmed, default=0.0):.2f} deg "
        f"[{letters}]{f', bad frame kept at {off} deg' if off else ''} ({seconds:.0f} s)"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[25, 46])
    parser.add_argument("--bad-frame", type=int, default=None)
    parser.add_argument("--splat-seconds", type=float, default=4.0)
    args = parser.parse_args()
    bad = () if args.bad_frame is None else (args.bad_frame,)
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            wide = {"path": CameraPath.WIDE, "texture": Texture.PLAIN_WALLS}
            scene = make_scene(SceneOptions(num_frames=8, width=320, height=240, seed=seed, **wide))
            folder = Path(tmp) / f"seed{seed}"
            written = write_scene(scene, folder / "scene")
            images = folder / "images"
            shutil.copytree(written, images, ignore=shutil.ignore_patterns("*.json", "*.npz"))
            model = folder / "sim.onnx"
            build_simulated_vggt(scene, model, SimulationOptions(seed=seed, bad_frames=bad, bad_rotation_deg=25.0))
            for quick in (False, True):
                line = _run(scene, images, model, folder / f"out_{quick}", quick, args.splat_seconds, bad)
                print(f"seed {seed} {'--quick ' if quick else 'default'}: {line}", flush=True)


if __name__ == "__main__":
    main()
