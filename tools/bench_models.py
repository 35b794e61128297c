#!/usr/bin/env python
"""Inference cost of exported models on this machine: seconds and peak memory per frame count.

Each measurement runs in a fresh process (so peak memory is that run's own) under an address-space
limit, so a frame count that does not fit fails cleanly ("does not fit") instead of invoking the
kernel's OOM killer. Photos come from a folder (cycled when fewer than the frame count) and go
through the family's own preprocessing, as in ``ffrecon run``.

    python tools/bench_models.py MODEL.onnx --photos PHOTO_DIR --frames 4 8 24
    python tools/bench_models.py MODEL.onnx --frames 2 4 8 --fit   # also fit peak = a + b S + c S^2

Prints one row per frame count; paste the table into docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

CHILD = r"""
import json, resource, sys, threading, time
from pathlib import Path
import onnxruntime as ort
on_gpu = "CUDAExecutionProvider" in ort.get_available_providers()
if not on_gpu:  # CUDA reserves address space far beyond what it uses: the limit is for the CPU provider
    limit = int(float(sys.argv[4]) * 2**30)
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
import numpy as np
from PIL import Image
from ffrecon.models.adapters import PreprocessMode, adapter_for
from ffrecon.models.runner import OnnxModel
model_path, photos, frames, repeats = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3]), int(sys.argv[5])
gpu_used, gpu_peak = None, [0]
try:  # the whole device's memory in use (NVML), polled while the model runs: onnxruntime has no peak counter
    import pynvml
    pynvml.nvmlInit()
    handle = pynvml.nvmlDeviceGetHandleByIndex(0)
    gpu_used = lambda: pynvml.nvmlDeviceGetMemoryInfo(handle).used
except Exception:
    pass
done = threading.Event()
def poll():
    while not done.is_set():
        gpu_peak[0] = max(gpu_peak[0], gpu_used())
        time.sleep(0.005)
gpu_base = gpu_used() if gpu_used else 0
if gpu_used:
    threading.Thread(target=poll, daemon=True).start()
files = sorted(p for p in photos.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
images = [np.asarray(Image.open(files[k % len(files)]).convert("RGB")) for k in range(frames)]
t0 = time.perf_counter()
model = OnnxModel(model_path)
load = time.perf_counter() - t0
adapter = adapter_for(model.family)
batch, _ = adapter.preprocess(images, PreprocessMode.CROP)
rss_loaded = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
times = []
try:
    for _ in range(1 + repeats):  # the first call also grows the arena and picks cuDNN's algorithms
        t0 = time.perf_counter()
        model.run({adapter.input_name: batch})
        times.append(time.perf_counter() - t0)
    status = "ok"
except Exception as exc:
    status = "does not fit: " + str(exc).splitlines()[0][:120]
done.set()
run = times[0] if times else float("nan")
warm = float(np.median(times[1:])) if len(times) > 1 else run
peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
print(json.dumps({"frames": frames, "status": status, "load_s": load, "run_s": run, "warm_s": warm,
                  "peak_gb": peak_gb, "gpu_peak_gb": (gpu_peak[0] - gpu_base) / 2**30 if gpu_used else None,
                  "loaded_gb": rss_loaded, "input_hw": list(batch.shape[2:]), "providers": list(model.providers)}))
"""


def measure(model: Path, photos: Path, frames: int, limit_gb: float, repeats: int = 0) -> dict:
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, str(model), str(photos), str(frames), str(limit_gb), str(repeats)],
        capture_output=True,
        text=True,
    )
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    if not lines:
        last_error = proc.stderr.strip().splitlines()[-1][:150] if proc.stderr.strip() else ""
        return {"frames": frames, "status": f"failed (exit {proc.returncode}): {last_error}"}
    return json.loads(lines[-1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model", type=Path)
    parser.add_argument(
        "--photos", type=Path, default=Path(__file__).resolve().parents[1].parent / "shared" / "data" / "lund"
    )
    parser.add_argument("--frames", type=int, nargs="+", default=[4, 8, 24])
    parser.add_argument(
        "--memory-limit-gb", type=float, default=20.0, help="address-space limit per run (default %(default)s)"
    )
    parser.add_argument(
        "--repeats", type=int, default=0, help="timed calls after the first (their median is 'warm s'; GPU: use 3)"
    )
    parser.add_argument(
        "--fit", action="store_true", help="fit peak memory = a + b S + c S^2 over the runs that fitted"
    )
    args = parser.parse_args()
    size = sum(p.stat().st_size for p in args.model.parent.glob(args.model.name + "*")) / 2**30
    print(f"{args.model.name}: {size:.2f} GB on disk")
    print("| frames | status | load s | first call s | warm call s | warm ms / frame | peak host GB | peak GPU GB |")
    print("|---|---|---|---|---|---|---|---|")
    rows = []
    for frames in args.frames:
        r = measure(args.model, args.photos, frames, args.memory_limit_gb, args.repeats)
        rows.append(r)
        if r["status"] == "ok":
            gpu = "-" if r.get("gpu_peak_gb") is None else f"{r['gpu_peak_gb']:.2f}"
            print(
                f"| {frames} | ok ({r['providers'][0].replace('ExecutionProvider', '')}) | {r['load_s']:.1f} "
                f"| {r['run_s']:.2f} | {r['warm_s']:.3f} | {1000 * r['warm_s'] / frames:.1f} | {r['peak_gb']:.2f} "
                f"| {gpu} |",
                flush=True,
            )
        else:
            print(f"| {frames} | {r['status']} | | | | | | |", flush=True)
    ok = [r for r in rows if r["status"] == "ok"]
    if args.fit and len(ok) >= 3:
        import numpy as np

        s = np.array([r["frames"] for r in ok], dtype=float)
        design = np.stack([np.ones_like(s), s, s**2], axis=1)
        key = "gpu_peak_gb" if ok[0].get("gpu_peak_gb") is not None else "peak_gb"
        coef, *_ = np.linalg.lstsq(design, np.array([r[key] for r in ok]), rcond=None)
        print(f"peak GB ~ {coef[0]:.3f} + {coef[1]:.4f} S + {coef[2]:.5f} S^2")
    return 0


if __name__ == "__main__":
    sys.exit(main())
