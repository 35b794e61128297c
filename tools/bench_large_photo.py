"""Very large photos: one 108-megapixel photo among five ordinary ones, a model and the splat, per size cap.

Usage (from the repository root):

    .venv/bin/python tools/bench_large_photo.py                        # caps 1600 (the default) and 0 (full size)
    .venv/bin/python tools/bench_large_photo.py --caps 1600 3200 0 --splat-seconds 10

The photos are ``../shared/data/lund`` 01-05 (1024x768) and 06 enlarged to 12000x9000 (bicubic, JPEG
quality 90), written to a temporary folder. Each cap is one ``ffrecon run --force`` in a fresh process
(``--force``: the shipped test net has random weights, so its gates fail); the table gives its exit
code, wall time and peak resident memory (``wait4``'s resource usage of the child), the size the splat trained the
large view at and its optimisation seconds against the budget, from report.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2

ROOT = Path(__file__).resolve().parent.parent
LUND = ROOT.parent / "shared" / "data" / "lund"


def make_photos(folder: Path, side: int) -> None:
    for k in range(1, 6):
        (folder / f"{k:02d}.jpg").write_bytes((LUND / f"{k:02d}.jpg").read_bytes())
    big = cv2.imread(str(LUND / "06.jpg"))
    big = cv2.resize(big, (side, side * 3 // 4), interpolation=cv2.INTER_CUBIC)
    cv2.imwrite(str(folder / "06_large.jpg"), big, [cv2.IMWRITE_JPEG_QUALITY, 90])


def run_one(photos: Path, out: Path, model: Path, cap: int, seconds: float) -> dict:
    command = [sys.executable, "-m", "ffrecon", "run", str(photos), "-o", str(out), "--model", str(model)]
    command += ["--force", "-q", "--max-image-size", str(cap), "--splat-seconds", str(seconds)]
    start = time.perf_counter()
    child = subprocess.Popen(command, cwd=ROOT)
    _, status, usage = os.wait4(child.pid, 0)  # this child's own peak resident memory
    child.returncode = code = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - start
    peak = usage.ru_maxrss / 2**20  # kB -> GB
    row = {"cap": cap, "exit": code, "wall_s": wall, "peak_gb": peak}
    report = out / "report.json"
    if report.is_file():
        data = json.loads(report.read_text())
        splat = data.get("splat") or {}
        row["largest_frame"] = max(data["inputs"]["sizes_wh"], key=lambda wh: wh[0] * wh[1])
        row["splat_max_side"] = splat.get("max_side")
        row["splat_optimize_s"] = (splat.get("timings_s") or {}).get("optimize")
        row["iterations"] = splat.get("iterations")
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--caps", type=int, nargs="+", default=[1600, 0], help="--max-image-size values, in order")
    parser.add_argument("--side", type=int, default=12000, help="long side of the large photo (12000: 108 MP)")
    parser.add_argument("--model", type=Path, default=ROOT / "models" / "tiny_vggt.onnx")
    parser.add_argument("--splat-seconds", type=float, default=60.0)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        photos = Path(tmp) / "photos"
        photos.mkdir()
        make_photos(photos, args.side)
        print(f"large photo {args.side}x{args.side * 3 // 4}; splat budget {args.splat_seconds:g} s")
        for cap in args.caps:
            row = run_one(photos, Path(tmp) / f"out_{cap}", args.model, cap, args.splat_seconds)
            print(json.dumps(row))
    return 0


if __name__ == "__main__":
    sys.exit(main())
