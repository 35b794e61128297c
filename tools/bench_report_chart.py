"""CPU seconds of the report's per-image error chart (``ffrecon.report.plots.error_bars_png``) at a run's size.

Usage (from the repository root):

    .venv/bin/python tools/bench_report_chart.py                     # this checkout's plots.py, 96 frames
    git show 57d0c2a^:ffrecon/report/plots.py > /tmp/plots_old.py   # another version, side by side
    .venv/bin/python tools/bench_report_chart.py --frames 96 250 --plots /tmp/plots_old.py ffrecon/report/plots.py

Each version draws the chart of three camera sets once to warm up, then ``--repeats`` times; the CPU seconds
(user + system of this process) of each drawing are printed.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _load(path: Path):
    spec = importlib.util.spec_from_file_location(f"plots_{abs(hash(path))}", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--plots", type=Path, nargs="+", default=[REPO / "ffrecon" / "report" / "plots.py"])
    parser.add_argument("--frames", type=int, nargs="+", default=[96])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    for n in args.frames:
        rng = np.random.default_rng(0)
        rotation = {label: 3 * rng.random(n) for label in ("model", "refined", "final")}
        centre = {label: rng.random(n) for label in rotation}
        names = [f"frame_{i:04d}.png" for i in range(n)]
        for path in args.plots:
            plots = _load(path)
            plots.error_bars_png(names, rotation, centre, rotation_threshold_deg=2.0)
            seconds = []
            for _ in range(args.repeats):
                start = time.process_time()
                plots.error_bars_png(names, rotation, centre, rotation_threshold_deg=2.0)
                seconds.append(time.process_time() - start)
            print(f"{n:5d} frames  {path}: CPU s " + " ".join(f"{s:.2f}" for s in seconds), flush=True)


if __name__ == "__main__":
    main()
