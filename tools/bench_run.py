"""Benchmark: the whole ``ffrecon run`` against COLMAP alone on the same images, per stage, at several frame counts.

For each frame count, a synthetic scene and its simulated VGGT model are made with
``ffrecon.demo.prepare_demo`` (cached under ``$FFRECON_CACHE``; ``--seed`` other than the demo's 0 gives
held-out scenes). Then, each in its own subprocess, timed wall-clock with its peak resident memory taken
from the kernel when it ends (``os.wait4``; the child's own and its children's high-water mark; the scene is made in a
child too, so that this process stays small: a child starts at its parent's high-water mark):

- COLMAP alone: ``run_colmap`` on the same images with the cross-check's default ``ColmapOptions`` (SIFT on
  the CPU, exhaustive pairing up to 150 images, incremental then global mapping) and the focal priors the
  pipeline would give it (EXIF only; none for these PNGs): the very code the pipeline's cross-check runs;
- ``ffrecon run IMAGES -o OUT --model MODEL --reference GT [--quick]``, one per mode. ``GT`` is the scene's
  ground truth written as a COLMAP model, so that the report scores the final cameras against it.

Per-stage seconds come from each run's ``report.json`` ("timings", with the run's own "startup": from the process's
start to the first stage, and "report": from the last stage to report.json's write); "other" is the wall time
measured here, outside the child, that no entry accounts for (stages that ran side by side count once).
Each stage's steps come from its own section's ``timings_s`` (wall) and ``cpu_s`` (user + system CPU, where
the stage records it: the COLMAP cross-check and the splat do), with how much of the stage they cover; each
run's whole CPU seconds (user + system, the child and its children, from ``os.wait4``) are the "cpu s" column,
and "xCPU" its ratio to COLMAP alone's. ffrecon runs in this script's own child (:func:`ffrecon_child`, the same
command) that also records each stage's wall and CPU seconds (stages side by side together), the imports
before the first stage, the report after the last, and the network's calls, whose wall and CPU the "without
the network" ratios leave out (issue 40's acceptance excludes inference). ``--cpus 0 0,1`` runs everything
once per CPU list under ``taskset`` and prints each stage's thread scaling. Accuracy is AUC@5
and the median rotation error against ground truth (the refined cameras; the feed-forward ones when
refinement did not run).
PSNR is the splat's mean held-out PSNR after cleaning. The growth summary fits ``seconds = a * n^b`` over
the frame counts (least squares in log-log) and prints ``b`` per stage. The splat stage ends within its budget
(``--splat-seconds``; 60 s by default) unless its training loss plateaus first, so its exponent says little
about its cost.

Usage (from the repository root)::

    .venv/bin/python tools/bench_run.py                                  # 24 48 96 frames of 640x480 (long)
    .venv/bin/python tools/bench_run.py --frames 8 --width 320 --height 240 --modes default --splat-seconds 10
    .venv/bin/python tools/bench_run.py --frames 24 48 --json bench_run.json --keep --out /tmp/bench_run
    .venv/bin/python tools/bench_run.py --frames 96 --modes quick default --no-splat --cpus 0 0,1  # issue 40

Timings on a shared machine are pessimistic; the load average is printed at the start and the end.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

# Columns of the table: report.json timing names, and groups of the small ones.
STAGES = ("capture", "feedforward", "colmap_matching", "colmap", "refine", "splat", "exports")
# with the checks between them (gates, dense evidence, comparisons): the cost of poses one can trust
POSE_STAGES = ("feedforward", "colmap_matching", "colmap", "refine", "checks")
CHECKS = ("gates", "evidence", "comparisons", "seed_comparison")
# Steps of COLMAP alone (its own timer).
STEPS = {"colmap": ("feature_extraction", "matching", "mapping")}
GIB = 2.0**30
MODES = ("default", "quick", "default+splat", "quick+splat")
STATS_FILE = "bench_stages.json"  # what an ffrecon child writes beside its output folder (ffrecon_child)
RESULT_FILE = "bench_colmap.json"  # what the COLMAP-alone child writes into its output folder


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, nargs="+", default=[24, 48, 96], help="frame counts (scenes)")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument(
        "--modes",
        nargs="+",
        choices=MODES,
        default=["default", "quick"],
        help="ffrecon runs: default, quick (--quick); '+splat' runs the splat whatever --no-splat says",
    )
    parser.add_argument("--seed", type=int, default=1, help="scene and model seed (the demo's is 0)")
    parser.add_argument("--splat-seconds", type=float, default=None, help="passed to ffrecon run")
    parser.add_argument("--no-splat", action="store_true", help="passed to ffrecon run (the pose stages alone)")
    parser.add_argument("--out", type=Path, default=None, help="work folder (default: a temporary one)")
    parser.add_argument("--keep", action="store_true", help="keep the runs' output folders")
    parser.add_argument("--json", type=Path, default=None, help="also save the results here")
    parser.add_argument(
        "--models",
        type=Path,
        nargs="+",
        default=None,
        help="exported .onnx files to run instead of the simulated model (rows labelled by file name)",
    )
    parser.add_argument(
        "--depth-stride",
        type=int,
        default=1,
        help="the simulated model stores depth at 1/N resolution (SimulationOptions.depth_stride; 4 for 1,000 frames)",
    )
    parser.add_argument("--no-colmap-alone", action="store_true", help="skip the COLMAP-alone row (no xCOLMAP)")
    parser.add_argument(
        "--drift",
        type=float,
        default=0.0,
        help="the simulated model drifts this many degrees per frame of a call (SimulationOptions.drift_deg_per_slot)",
    )
    parser.add_argument(
        "--without-loops-too",
        action="store_true",
        help="each mode also once with --no-loop-chunks (rows 'MODE no-loops')",
    )
    parser.add_argument(
        "--colmap-pairing",
        choices=("auto", "exhaustive", "sequential"),
        default="auto",
        help="COLMAP alone's pairing (ColmapOptions.pairing; auto: exhaustive up to 150 images, sequential past that)",
    )
    parser.add_argument(
        "--colmap-mapping-seconds",
        type=int,
        default=None,
        help="COLMAP alone's bound per mapper (ColmapOptions.max_mapping_seconds; default: the pipeline's)",
    )
    parser.add_argument(
        "--cpus",
        nargs="+",
        default=None,
        metavar="LIST",
        help="run every method once per CPU list under 'taskset -c LIST' (e.g. --cpus 0 0,1: thread scaling, one "
        "core against two); default: no taskset",
    )
    parser.add_argument("--ffrecon-child", type=Path, default=None, help=argparse.SUPPRESS)  # see main()
    parser.add_argument("--colmap-only", nargs=2, type=Path, metavar=("IMAGES", "OUT"), help=argparse.SUPPRESS)
    parser.add_argument("--truth", type=Path, default=None, help=argparse.SUPPRESS)  # scene folder, for the child
    parser.add_argument("--prepare-only", nargs=5, type=int, default=None, help=argparse.SUPPRESS)  # prepare()'s child
    return parser


def machine() -> dict:
    """CPU count, load average, memory and versions, for the top of the output."""
    mem_gb = float("nan")
    meminfo = Path("/proc/meminfo")
    if meminfo.is_file():
        for line in meminfo.read_text().splitlines():
            if line.startswith("MemTotal:"):
                mem_gb = float(line.split()[1]) * 1024 / GIB
    import pycolmap

    import ffrecon

    return {
        "cpus": os.cpu_count(),
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "memory_gb": round(mem_gb, 1),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "pycolmap": pycolmap.__version__,
        "ffrecon": ffrecon.__version__,
    }


def quick_available() -> bool:
    """Whether ``ffrecon run`` knows ``--quick`` (asked of the command itself)."""
    cmd = [sys.executable, "-m", "ffrecon", "run", "--help"]
    return "--quick" in subprocess.run(cmd, capture_output=True, text=True, check=True).stdout


class GpuPeak:
    """The first GPU's memory in use, polled (NVML) while a child runs, above what was in use before it;
    ``peak_gb`` is None without NVML (no NVIDIA driver, or no ``nvidia-ml-py``)."""

    def __init__(self) -> None:
        self.peak_gb: float | None = None
        try:
            import pynvml

            pynvml.nvmlInit()
            handle = pynvml.nvmlDeviceGetHandleByIndex(0)
            self._used = lambda: pynvml.nvmlDeviceGetMemoryInfo(handle).used
        except Exception:  # NVML's errors are its own types; any of them means "not measurable here"
            self._used = None

    def __enter__(self) -> GpuPeak:
        if self._used is not None:
            self._base, self._peak, self._done = self._used(), 0, threading.Event()
            self._thread = threading.Thread(target=self._poll, daemon=True)
            self._thread.start()
        return self

    def _poll(self) -> None:
        while not self._done.wait(0.02):
            self._peak = max(self._peak, self._used())

    def __exit__(self, *exc: object) -> None:
        if self._used is not None:
            self._done.set()
            self._thread.join()
            self.peak_gb = max(self._peak - self._base, 0) / GIB


def measured(cmd: list[str], log_path: Path) -> tuple[int, float, float, float | None, float]:
    """Run ``cmd`` (output to ``log_path``): ``(exit code, wall seconds, peak resident GB, peak GPU GB or None,
    CPU seconds)``; the CPU seconds are user + system of the child and of its own waited-for children.

    The peak is the kernel's high-water mark of the child (and of its own waited-for children), from
    ``os.wait4``: ``ru_maxrss`` of RUSAGE_CHILDREN would be the largest of all children so far.
    """
    with open(log_path, "w") as log, GpuPeak() as gpu:
        start = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - start
    proc.returncode = os.waitstatus_to_exitcode(status)  # reaped here; tell Popen so it does not wait again
    cpu = usage.ru_utime + usage.ru_stime
    return proc.returncode, wall, usage.ru_maxrss * 1024 / GIB, gpu.peak_gb, cpu  # ru_maxrss is in KiB on Linux


def _tail(path: Path, lines: int = 8) -> str:
    return "\n".join(path.read_text(errors="replace").splitlines()[-lines:]) if path.is_file() else ""


# --- the COLMAP-alone child ---------------------------------------------------------------------------


def _truth_poses(scene_dir: Path, names: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth ``[N, 3, 4]`` cam_from_world of ``names`` from ``ground_truth.json`` (not the images)."""
    truth = json.loads((scene_dir / "ground_truth.json").read_text())
    by_name = {f["name"]: np.asarray(f["cam_from_world"], np.float64) for f in truth["frames"]}
    have = np.array([n in by_name for n in names])
    return np.stack([by_name.get(n, np.eye(3, 4)) for n in names]), have


def colmap_child(images: Path, out: Path, scene_dir: Path | None, pairing: str, mapping_s: int | None) -> None:
    """COLMAP alone, as the pipeline's cross-check runs it; writes ``out/RESULT_FILE``.

    Imports stay inside so that this process holds only what COLMAP needs (its peak memory is measured).
    """
    from ffrecon.capture.images import focal_prior_px, list_images, read_exif
    from ffrecon.sfm.crosscheck.options import ColmapOptions, PairingMode
    from ffrecon.sfm.crosscheck.run import run_colmap
    from ffrecon.sfm.features import image_sizes_wh

    paths, _ = list_images(images)
    names = [p.name for p in paths]
    sizes = image_sizes_wh(images, names)
    priors = [focal_prior_px(*size, *read_exif(p)[1:]) if size else None for p, size in zip(paths, sizes)]
    start = time.perf_counter()
    options = ColmapOptions(pairing=PairingMode(pairing))
    if mapping_s is not None:
        options = dataclasses.replace(options, max_mapping_seconds=mapping_s)
    result = run_colmap(images, names, options, out, focal_prior_px=priors)
    row = {
        "seconds": time.perf_counter() - start,
        "steps": result.timings.to_report(),
        "num_images": len(names),
        "registered": result.num_registered,
        "mapper": None if result.mapper is None else result.mapper.value,
        "pairing": result.pairing.value,
    }
    if scene_dir is not None:
        from ffrecon.geometry.metrics import pose_errors

        truth, have = _truth_poses(scene_dir, names)
        errors = pose_errors(result.cam_from_world[have], truth[have], result.registered[have])
        row.update(auc5=errors.auc[5], med_rot=errors.median_rotation_deg, versus="ground truth")
    (out / RESULT_FILE).write_text(json.dumps(row))


# --- the ffrecon child: the command itself, with the CPU seconds of each stage ------------------------


def ffrecon_child(stats_path: Path, argv: list[str]) -> int:
    """``ffrecon ARGV`` in this process, recording into ``stats_path`` (JSON) the wall and CPU seconds (user +
    system, :func:`ffrecon.timing.cpu_seconds`) of each step of the pipeline's plan (a stage, or stages side by
    side: their CPU is the process's, so it is theirs together), of the imports and parsing before the first
    stage and of what follows the last (the report), and of the network's calls (``OnnxModel.run``: wall, and
    the process's CPU meanwhile, which counts the work beside the inference too).

    ``report.json`` holds each stage's wall seconds but not its CPU seconds: this wraps the plan's step runner
    (:meth:`ffrecon.state.StagePlan.run`) from outside instead of changing the package for a benchmark.
    """
    t0 = time.perf_counter()
    import ffrecon.models.runner as runner
    import ffrecon.state as plan_module
    from ffrecon.cli import main as ffrecon_main
    from ffrecon.timing import Clock, cpu_seconds

    started = Clock.process_start() or Clock.now("bench_run child called")  # as the ffrecon command times it

    stats: dict = {"steps": [], "inference": {"calls": 0, "wall_s": 0.0, "cpu_s": 0.0}}
    plan_run, model_run = plan_module.StagePlan.run, runner.OnnxModel.run

    def timed(into: dict, fn, *args):
        wall, cpu = time.perf_counter(), cpu_seconds()
        try:
            return fn(*args)
        finally:
            into["wall_s"] += time.perf_counter() - wall
            into["cpu_s"] += cpu_seconds() - cpu

    def plan_step(self, state, step):
        names = [stage.name for stage in getattr(step, "stages", (step,))]
        stats.setdefault("first", (time.perf_counter() - t0, cpu_seconds()))
        stats["steps"].append(entry := {"stages": names, "wall_s": 0.0, "cpu_s": 0.0})
        try:
            return timed(entry, plan_run, self, state, step)
        finally:
            stats["last"] = (time.perf_counter() - t0, cpu_seconds())

    def model_call(self, feeds):
        stats["inference"]["calls"] += 1
        return timed(stats["inference"], model_run, self, feeds)

    plan_module.StagePlan.run, runner.OnnxModel.run = plan_step, model_call
    try:
        return ffrecon_main(argv, started=started)
    finally:
        stats["end"] = (time.perf_counter() - t0, cpu_seconds())
        plan_module.StagePlan.run, runner.OnnxModel.run = plan_run, model_run
        stats_path.write_text(json.dumps(stats))


# --- the parent: scenes, runs, rows -------------------------------------------------------------------


def prepare(frames: int, width: int, height: int, seed: int, depth_stride: int = 1, drift: float = 0.0):
    """The scene and simulated model (cached), and the seconds it took; made in a child process.

    Linux carries a process's resident high-water mark across ``fork`` and ``exec`` (``ru_maxrss`` of a
    child starts at its parent's size when it forked), so a bench that had built a 500-frame scene itself
    (4.8 GB) reported that figure for every run after it: this process stays small instead.
    """
    from ffrecon.demo import DemoInputs

    start = time.perf_counter()
    cmd = [sys.executable, str(Path(__file__).resolve()), "--prepare-only", str(frames), str(width), str(height)]
    cmd += [str(seed), str(depth_stride), "--drift", str(drift)]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"preparing the {frames}-frame scene failed:\n{done.stderr[-2000:]}")
    paths = json.loads(done.stdout.strip().splitlines()[-1])
    return DemoInputs(**{k: Path(v) for k, v in paths.items()}), time.perf_counter() - start


def _prepare_here(frames: int, width: int, height: int, seed: int, depth_stride: int, drift: float) -> None:
    """The child of :func:`prepare`: makes (or finds) the scene and prints its paths as JSON."""
    from ffrecon.demo import DemoOptions, prepare_demo
    from ffrecon.synthetic import SceneOptions

    scene = SceneOptions(num_frames=frames, width=width, height=height, seed=seed)
    simulation = {"bad_frames": [7]} | ({"depth_stride": depth_stride} if depth_stride != 1 else {})
    simulation |= {"drift_deg_per_slot": drift} if drift else {}
    inputs = prepare_demo(DemoOptions(scene=scene, simulation=simulation))
    print(json.dumps({k: str(v) for k, v in dataclasses.asdict(inputs).items()}))


def write_reference(scene_dir: Path, out: Path) -> Path:
    """The ground truth of ``scene_dir`` as a COLMAP model (cameras and poses, no points), for ``--reference``."""
    from ffrecon.colmap_io import reconstruction_from_cameras, write_reconstruction
    from ffrecon.types import PinholeCamera

    truth = json.loads((scene_dir / "ground_truth.json").read_text())
    c = truth["camera"]
    camera = PinholeCamera(int(c["width"]), int(c["height"]), c["fx"], c["fy"], c["cx"], c["cy"])
    names = [f["name"] for f in truth["frames"]]
    poses = np.array([f["cam_from_world"] for f in truth["frames"]], np.float64)
    rec = reconstruction_from_cameras(names, poses, [camera] * len(names))
    return write_reconstruction(rec, out)


def run_colmap_alone(images: Path, scene_dir: Path, out: Path, args, cpus: str | None = None) -> dict:
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    cmd = [sys.executable, str(Path(__file__).resolve()), "--colmap-only", str(images), str(out)]
    cmd += ["--colmap-pairing", args.colmap_pairing]
    if args.colmap_mapping_seconds is not None:
        cmd += ["--colmap-mapping-seconds", str(args.colmap_mapping_seconds)]
    log = out.parent / f"{out.name}.log"
    code, wall, peak, _, cpu = measured(pinned([*cmd, "--truth", str(scene_dir)], cpus), log)
    row = {"method": "COLMAP alone", "exit": code, "wall_s": wall, "peak_gb": peak, "cpu_s": cpu}
    if code != 0 or not (out / RESULT_FILE).is_file():
        row["error"] = _tail(log)
        return row
    child = json.loads((out / RESULT_FILE).read_text())
    steps = child["steps"]
    row.update(
        stages={"colmap": steps["total"]},
        other_s=wall - steps["total"],
        steps={f"colmap {k}": steps.get(k, 0.0) for k in STEPS["colmap"]},
        registered=f"{child['registered']}/{child['num_images']}",
        auc5=child.get("auc5"),
        med_rot=child.get("med_rot"),
        colmap_setup=f"{child['pairing']} pairing, {child['mapper']} mapper",
    )
    return row


def ffrecon_command(images: Path, model: Path, out: Path, reference: Path, mode: str, args) -> list[str]:
    """``ffrecon run ...`` for ``mode`` (``default``/``quick``, ``+splat``, `` no-loops``), run by this script's
    :func:`ffrecon_child` (the same command, with each stage's CPU seconds written to ``OUT/../STATS_FILE``)."""
    cmd = ["run", str(images), "-o", str(out), "--model", str(model), "--reference", str(reference), "--overwrite"]
    if mode.startswith("quick"):
        cmd.append("--quick")
    if mode.endswith("no-loops"):
        cmd.append("--no-loop-chunks")
    if args.no_splat and "+splat" not in mode:
        cmd.append("--no-splat")  # and no --splat-seconds: ffrecon refuses a budget for a splat it does not make
    elif args.splat_seconds is not None:
        cmd += ["--splat-seconds", str(args.splat_seconds)]
    stats = out.parent / f"{out.name}.{STATS_FILE}"
    return [sys.executable, str(Path(__file__).resolve()), "--ffrecon-child", str(stats), "--", *cmd]


def pinned(cmd: list[str], cpus: str | None) -> list[str]:
    """``cmd`` under ``taskset -c cpus`` (None: as it is).

    >>> pinned(["x"], "0")
    ['taskset', '-c', '0', 'x']
    """
    return cmd if cpus is None else ["taskset", "-c", cpus, *cmd]


def stage_cpu(stats: dict, ran: set[str]) -> dict:
    """CPU and wall seconds by step of the plan from :func:`ffrecon_child`'s stats: ``{"cpu": {step: s}, "wall":
    {step: s}, "before": (wall, cpu), "after": (wall, cpu), "inference": {...}}``; a step is named by the stages of
    it that ran (``ran``; side by side joined with '+'), steps where none ran are left out."""
    cpu, wall = {}, {}
    for step in stats.get("steps", []):
        names = [n for n in step["stages"] if n in ran]
        if names:
            key = "+".join(names)
            cpu[key] = cpu.get(key, 0.0) + step["cpu_s"]
            wall[key] = wall.get(key, 0.0) + step["wall_s"]
    first, last, end = stats.get("first"), stats.get("last"), stats.get("end")
    out = {"cpu": cpu, "wall": wall, "inference": stats.get("inference") or {}}
    if first and last and end:
        out["before"] = tuple(first)
        out["after"] = (end[0] - last[0], end[1] - last[1])
    return out


def _accuracy(report: dict) -> dict:
    """AUC@5 and median rotation against the reference model (ground truth): of every estimate, and the
    headline one of the final cameras (those the run exported: refined, else feed-forward, else COLMAP's)."""
    scores = {
        comp["estimate"]: {
            "auc5": comp["metrics"]["AUC@5"],
            "med_rot": comp["metrics"]["median_rotation_deg"],
            "registered": f"{comp['metrics']['num_registered']}/{comp['metrics']['num_images']}",
        }
        for comp in (report.get("pose_errors") or {}).values()
        if comp["reference"] == "reference model"
    }
    final = (report.get("exports") or {}).get("cameras")
    scored = final if final in scores else next((e for e in ("refined", "feed-forward", "COLMAP") if e in scores), None)
    return {"accuracy": scores, **({"scored": scored, **scores[scored]} if scored else {})}


def stage_steps(report: dict) -> tuple[dict, dict, dict]:
    """``(steps, cpu, coverage)`` of a run's ``report.json``: ``{"stage step": wall s}`` and ``{"stage step": CPU
    s}`` from each stage's section (``timings_s``, ``cpu_s``), and ``{stage: steps' sum / stage's seconds}``."""
    steps, cpu, coverage = {}, {}, {}
    for stage, t in report.get("timings", {}).items():
        section = report.get(stage)
        own = section.get("timings_s") if isinstance(section, dict) else None
        if not isinstance(own, dict) or t.get("reused"):
            continue
        own_cpu = section.get("cpu_s") or {}
        for step, seconds in own.items():
            if step != "total":
                steps[f"{stage} {step}"] = seconds
                if own_cpu.get(step) is not None:
                    cpu[f"{stage} {step}"] = own_cpu[step]
        if t["seconds"] > 0:
            coverage[stage] = sum(v for k, v in own.items() if k != "total") / t["seconds"]
    return steps, cpu, coverage


def stages_wall(report: dict) -> float:
    """The stages' wall clock: their sum, stages that ran side by side counted once (``concurrent_stages``)."""
    total = sum(t["seconds"] for t in report.get("timings", {}).values())
    return total - sum(g["sum_seconds"] - g["wall_seconds"] for g in report.get("concurrent_stages", []))


def report_row(report: dict, wall: float) -> dict:
    """Stage seconds, each stage's steps, accuracy and splat PSNR from a run's ``report.json``."""
    timings = {name: t["seconds"] for name, t in report.get("timings", {}).items()}
    stages = {name: timings.get(name, 0.0) for name in STAGES}
    stages["checks"] = sum(timings.get(name, 0.0) for name in CHECKS)
    unknown = sorted(set(timings) - set(STAGES) - set(CHECKS))
    for name in unknown:  # stages this script does not know yet still count, under their own names
        stages[name] = timings[name]
    splat = report.get("splat") or {}
    steps, step_cpu, coverage = stage_steps(report)
    row = {
        "stages": stages,
        "other_s": wall - stages_wall(report),
        "step_cpu": step_cpu,
        "coverage": coverage,
        "splat_budget_s": splat.get("budget_s"),
        "splat_skipped": splat.get("skipped_steps") or {},
        "skipped": [s["stage"] for s in report.get("skipped_stages", [])],
        "verdict": report.get("verdict", {}).get("status"),
        "steps": steps,
        "psnr": (splat.get("heldout_mean") or {}).get("psnr_cleaned"),
        "splat_iterations": splat.get("iterations"),
        "splat_backend": splat.get("backend"),
        "splat_it_per_s": splat.get("iterations_per_second"),
        # held-out PSNR (before cleaning) at the last evaluation within 30 and 60 s of training
        "psnr_at_s": {
            t: max(
                ((p["seconds"], p["psnr"]) for p in splat.get("heldout_curve", []) if p["seconds"] <= t),
                default=(0, None),
            )[1]
            for t in (30, 60)
        },
        "providers": ((report.get("feedforward") or {}).get("model") or {}).get("providers"),
        # each stage's peak resident memory (report.json; the first of two stages side by side holds both)
        "stage_peak_gb": {
            name: t["peak_rss_gb"] for name, t in report.get("timings", {}).items() if t.get("peak_rss_gb") is not None
        },
    }
    row.update(_accuracy(report))
    return row


def run_ffrecon(
    inputs, mode: str, work: Path, reference: Path, args, model: Path | None = None, cpus: str | None = None
) -> dict:
    label = (mode if model is None else f"{mode} {model.stem}") + cpus_label(cpus)
    stem = "ffrecon_" + "".join(c if c.isalnum() or c in "+-." else "_" for c in label)
    out, log = work / stem, work / f"{stem}.log"
    cmd = ffrecon_command(inputs.images, model or inputs.model, out, reference, mode, args)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    code, wall, peak, gpu_peak, cpu = measured(pinned(cmd, cpus), log)
    row = {"method": f"ffrecon {label}", "exit": code, "wall_s": wall, "peak_gb": peak, "gpu_peak_gb": gpu_peak}
    row.update(cpu_s=cpu, load=load, cpus=cpus, mode=mode)
    if not (out / "report.json").is_file():
        row["error"] = _tail(log)
        return row
    report = json.loads((out / "report.json").read_text())
    row.update(report_row(report, wall))
    stats = out.parent / f"{out.name}.{STATS_FILE}"
    if stats.is_file():
        ran = {name for name, t in report.get("timings", {}).items() if not t.get("reused")}
        row["by_step"] = stage_cpu(json.loads(stats.read_text()), ran)
        row["other_parts"] = other_parts(json.loads(stats.read_text()), row["other_s"], wall, report)
    if (out / "sparse" / "0").is_dir():
        row["loop_drift_pct"] = loop_drift_pct(out / "sparse" / "0", inputs.scene_dir)
    return row


def other_parts(stats: dict, other_s: float, wall: float, report: dict | None = None) -> dict:
    """Where a run's "other" seconds (wall that no entry of ``report.json``'s timings holds) went, from
    :func:`ffrecon_child`'s stats and the run's ``report``.

    Where the report times the run's own "startup" (from the process's start to the first stage) and "report"
    (from the last stage to report.json's write): what follows the report's entry (report.json written, the
    results swapped into OUT, the summary), the gaps between stages (inside the plan's steps but outside the
    stages' seconds: records, resume keys), and the rest: the process's start before the kernel's record of it
    and its exit. From an older report without them: the imports and parsing before the first stage, the report
    after the last, the interpreter's start and exit (the child's wall outside its own clock), and the gaps.

    >>> other_parts({"first": (3.0, 2.9), "last": (60.0, 70.0), "end": (62.0, 72.0)}, 7.0, 63.5)
    {'imports+parse': 3.0, 'report+summary': 2.0, 'start+exit': 1.5, 'between stages': 0.5}
    >>> report = {"timings": {"startup": {"seconds": 3.5}, "a": {"seconds": 56.6}, "report": {"seconds": 1.9}}}
    >>> other_parts({"first": (3.0, 2.9), "last": (60.0, 70.0), "end": (62.0, 72.0)}, 0.6, 62.6, report)
    {'after the report': 0.1, 'between stages': 0.4, 'start+exit': 0.1}
    """
    first, last, end = stats.get("first"), stats.get("last"), stats.get("end")
    if not (first and last and end):
        return {}
    timings = (report or {}).get("timings", {})
    own = {name: timings.get(name, {}).get("seconds") for name in ("startup", "report")}
    if None in own.values():
        parts = {"imports+parse": first[0], "report+summary": end[0] - last[0], "start+exit": wall - end[0]}
    else:
        stages = stages_wall(report)
        parts = {
            "after the report": end[0] - last[0] - own["report"],
            "between stages": last[0] - first[0] - (stages - own["startup"] - own["report"]),
        }
    parts[next(k for k in ("between stages", "start+exit") if k not in parts)] = other_s - sum(parts.values())
    return {k: round(v, 4) for k, v in parts.items()}


def cpus_label(cpus: str | None) -> str:
    """`` [cpus LIST]`` for a run under taskset, else nothing."""
    return "" if cpus is None else f" [cpus {cpus}]"


def loop_drift_pct(model_dir: Path, scene_dir: Path) -> float | None:
    """The loop's drift in % of the path length: how far the distance between the first and the last frame
    (which revisits it: the scenes' orbit is one full loop) is from the truth, after a Sim(3) of all centres."""
    import pycolmap

    from ffrecon.colmap_io import cam_from_world_by_name
    from ffrecon.geometry.alignment import umeyama
    from ffrecon.geometry.poses import camera_centers

    truth = json.loads((scene_dir / "ground_truth.json").read_text())
    names = [f["name"] for f in truth["frames"]]
    poses, registered = cam_from_world_by_name(pycolmap.Reconstruction(model_dir), names)
    if not (registered[0] and registered[-1]) or registered.sum() < 3:
        return None
    ref = camera_centers(np.array([f["cam_from_world"] for f in truth["frames"]], np.float64))
    est = umeyama(camera_centers(poses[registered]), ref[registered]).apply(camera_centers(poses[registered]))
    gap = abs(np.linalg.norm(est[0] - est[-1]) - np.linalg.norm(ref[0] - ref[-1]))
    return float(100 * gap / np.linalg.norm(np.diff(ref, axis=0), axis=1).sum())


def bench_frames(frames: int, args, root: Path) -> list[dict]:
    """Every method on one scene of ``frames`` frames (once per ``--cpus`` list); the rows carry ``frames``."""
    inputs, prep_s = prepare(frames, args.width, args.height, args.seed, args.depth_stride, args.drift)
    size = f"{args.width}x{args.height}"
    print(f"\n{frames} frames of {size}: scene and model ready in {prep_s:.1f} s ({inputs.scene_dir})")
    work = root / f"n{frames}"
    work.mkdir(parents=True, exist_ok=True)
    reference = write_reference(inputs.scene_dir, work / "ground_truth_model")
    rows = []
    for cpus in args.cpus or [None]:
        alone = work / ("colmap_alone" + "".join(c if c.isalnum() else "_" for c in cpus_label(cpus)))
        group = []
        if not args.no_colmap_alone:
            load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
            group.append(run_colmap_alone(inputs.images, inputs.scene_dir, alone, args, cpus))
            group[0].update(method="COLMAP alone" + cpus_label(cpus), load=load, cpus=cpus, mode="colmap")
        for model in args.models or [None]:
            modes = [m + suffix for m in args.modes for suffix in ("", " no-loops")[: 1 + args.without_loops_too]]
            group += [run_ffrecon(inputs, mode, work, reference, args, model, cpus) for mode in modes]
        compare_with_colmap(group)
        rows += group
    for row in rows:
        row["frames"] = frames
    if not args.keep:
        shutil.rmtree(work, ignore_errors=True)
    return rows


def compare_with_colmap(rows: list[dict]) -> None:
    """Each row's ratios to the first row when it is COLMAP alone (NaN otherwise): wall (``ratio``), CPU
    (``cpu_ratio``), and both without the network's calls (``ex_inference``: wall less the calls' wall, CPU less
    the process's CPU during them); the pose stages' speed-up over COLMAP alone's own seconds."""
    first = rows[0] if rows and rows[0]["method"].startswith("COLMAP alone") and "error" not in rows[0] else None
    colmap_wall = first["wall_s"] if first else float("nan")
    colmap_cpu = first["cpu_s"] if first else float("nan")
    colmap_s = first["stages"]["colmap"] if first else float("nan")
    for row in rows:
        row.update(ratio=row["wall_s"] / colmap_wall, cpu_ratio=row["cpu_s"] / colmap_cpu)
        inference = (row.get("by_step") or {}).get("inference") or {}
        row["ex_inference"] = {
            "wall_s": row["wall_s"] - inference.get("wall_s", 0.0),
            "cpu_s": row["cpu_s"] - inference.get("cpu_s", 0.0),
        }
        row["ex_inference"].update(
            ratio=row["ex_inference"]["wall_s"] / colmap_wall, cpu_ratio=row["ex_inference"]["cpu_s"] / colmap_cpu
        )
        if not row["method"].startswith("COLMAP alone") and "stages" in row:
            # The pose stages (feed-forward, cross-check, refinement) against COLMAP alone's own seconds
            row["pose_s"] = sum(row["stages"].get(k, 0.0) for k in POSE_STAGES)
            row["pose_speedup"] = colmap_s / row["pose_s"]


# --- printing -----------------------------------------------------------------------------------------


def _num(value, fmt: str, width: int) -> str:
    return f"{'-':>{width}}" if value is None or not np.isfinite(value) else f"{value:>{width}{fmt}}"


def print_table(rows: list[dict]) -> None:
    named = {k for r in rows for k in r.get("stages", {})}
    extra = sorted(named - set(STAGES) - {"checks", "startup", "report"})
    # the run's own entries first and last: from the process's start to the first stage, after the last stage
    columns = [*({"startup"} & named), *STAGES, "checks", *extra, *({"report"} & named)]
    short = {"feedforward": "ff", "exports": "export", "colmap_matching": "colmatch"}
    head = "".join(f"{short.get(c, c)[:8]:>9}" for c in columns)
    print(f"{'method':<24}{'wall s':>8}{'xCOLMAP':>8}{head}{'other':>8}{'cpu s':>8}{'xCPU':>6}{'peakGB':>7}", end="")
    print(f"{'exit':>5}{'reg':>7}{'AUC@5':>7}{'medrot':>8}{'PSNR':>6}")
    for r in rows:
        if "error" in r:
            print(f"{r['method']:<24}{r['wall_s']:>8.1f}  failed (exit {r['exit']}):\n{r['error']}")
            continue
        cells = "".join(_num(r["stages"].get(c), ".2f", 9) if c in r["stages"] else f"{'':>9}" for c in columns)
        print(
            f"{r['method']:<24}{r['wall_s']:>8.2f}{_num(r.get('ratio'), '.2f', 8)}{cells}{r['other_s']:>8.2f}"
            f"{_num(r.get('cpu_s'), '.1f', 8)}{_num(r.get('cpu_ratio'), '.2f', 6)}{r['peak_gb']:>7.2f}{r['exit']:>5}"
            f"{r.get('registered', '-'):>7}{_num(r.get('auc5'), '.3f', 7)}"
            f"{_num(r.get('med_rot'), '.3f', 8)}{_num(r.get('psnr'), '.1f', 6)}"
        )
    for r in rows:
        print_details(r)


def print_details(r: dict) -> None:
    """The lines under the table for one row: load, CPU by step, splat, steps, coverage, memory, accuracy."""
    if r.get("load") is not None:
        print(f"  {r['method']}: load average {r['load']:.2f} as it started")
    ex = r.get("ex_inference")
    step = r.get("by_step")
    if step and ex:
        inf = step.get("inference") or {}
        print(
            f"  {r['method']} without the network's {inf.get('calls', 0)} calls ({inf.get('wall_s', 0):.2f} s wall, "
            f"{inf.get('cpu_s', 0):.2f} s CPU meanwhile): wall {ex['wall_s']:.2f} s = {_num(ex['ratio'], '.2f', 0)}x "
            f"COLMAP alone, CPU {ex['cpu_s']:.1f} s = {_num(ex['cpu_ratio'], '.2f', 0)}x"
        )
    if step:
        cells = [f"{k} {step['wall'][k]:.2f} (cpu {v:.2f})" for k, v in step["cpu"].items()]
        if "before" in step:
            cells = [f"imports+parse {step['before'][0]:.2f} (cpu {step['before'][1]:.2f})", *cells]
            cells.append(f"report+summary {step['after'][0]:.2f} (cpu {step['after'][1]:.2f})")
        print(f"  {r['method']} wall (CPU) by step: " + ", ".join(cells))
    if r.get("other_parts"):
        parts = ", ".join(f"{k} {v:.2f}" for k, v in r["other_parts"].items())
        print(f"  {r['method']} other {r['other_s']:.2f} s ({r['other_s'] / r['wall_s']:.1%} of the wall): {parts}")
    if r.get("splat_backend"):
        at = ", ".join(f"{t} s {_num(p, '.2f', 0)} dB" for t, p in (r.get("psnr_at_s") or {}).items())
        gpu = "" if r.get("gpu_peak_gb") is None else f"; peak GPU {r['gpu_peak_gb']:.1f} GB"
        print(
            f"  {r['method']}: model on {', '.join(r.get('providers') or ['-'])}{gpu}; splat {r['splat_backend']} "
            f"{_num(r.get('splat_it_per_s'), '.1f', 0)} it/s, held-out PSNR at {at}"
        )
    if r.get("steps"):
        cpu = r.get("step_cpu") or {}
        cells = (f"{k} {v:.2f}" + (f" (cpu {cpu[k]:.2f})" if k in cpu else "") for k, v in r["steps"].items())
        print(f"  {r['method']} steps: " + ", ".join(cells))
    if r.get("coverage"):
        print(f"  {r['method']} steps / stage: " + ", ".join(f"{k} {v:.0%}" for k, v in r["coverage"].items()))
    if r.get("splat_skipped"):
        print(
            f"  {r['method']} splat steps the budget left out: "
            + "; ".join(f"{k}: {v}" for k, v in r["splat_skipped"].items())
        )
    if r.get("stage_peak_gb"):
        peaks = ", ".join(f"{k} {v:.2f}" for k, v in r["stage_peak_gb"].items())
        print(f"  {r['method']} peak GB by stage: {peaks}")
    others = {e: a for e, a in r.get("accuracy", {}).items() if e != r.get("scored")}
    notes = [f"scored: {r['scored']} cameras"] if r.get("scored") else []
    notes += [f"{e} {a['registered']} AUC@5 {_num(a['auc5'], '.3f', 0)}" for e, a in others.items()]
    if r.get("skipped"):
        notes.append(f"skipped: {', '.join(r['skipped'])}")
    if r.get("colmap_setup"):
        notes.append(r["colmap_setup"])
    if r.get("pose_s") is not None:
        speedup = _num(r.get("pose_speedup"), ".2f", 0)
        notes.append(f"pose stages {r['pose_s']:.1f} s, {speedup}x faster than COLMAP alone")
    if r.get("loop_drift_pct") is not None:
        notes.append(f"loop drift {r['loop_drift_pct']:.3f}% of the path")
    if notes:
        print(f"  {r['method']}: {'; '.join(notes)}")


def scaling(rows: list[dict]) -> list[tuple[str, str, float, float]]:
    """Thread scaling between the first and the last ``--cpus`` list: ``(method, step, seconds on the first,
    seconds on the last)`` per method and per stage or step that took over 2 s on either, the whole wall first.

    >>> rows = [{"mode": "quick", "cpus": "0", "wall_s": 9.0, "stages": {"refine": 4.0, "gates": 0.1}},
    ...         {"mode": "quick", "cpus": "0,1", "wall_s": 5.0, "stages": {"refine": 2.5, "gates": 0.1}}]
    >>> scaling(rows)
    [('quick', 'wall', 9.0, 5.0), ('quick', 'refine', 4.0, 2.5)]
    """
    cpus = list(dict.fromkeys(r.get("cpus") for r in rows if r.get("cpus") is not None))
    out = []
    if len(cpus) < 2:
        return out
    for mode in dict.fromkeys(r.get("mode") for r in rows):
        by_cpus = {r["cpus"]: r for r in rows if r.get("mode") == mode and "error" not in r}
        few, many = by_cpus.get(cpus[0]), by_cpus.get(cpus[-1])
        if few is None or many is None:
            continue
        out.append((mode, "wall", few["wall_s"], many["wall_s"]))
        for source in ("stages", "steps"):
            for name, seconds in (few.get(source) or {}).items():
                other = (many.get(source) or {}).get(name)
                if other is not None and max(seconds, other) > 2.0:
                    out.append((mode, name, seconds, other))
    return out


def print_scaling(rows: list[dict]) -> None:
    found = scaling(rows)
    if not found:
        return
    cpus = list(dict.fromkeys(r.get("cpus") for r in rows if r.get("cpus") is not None))
    print(f"\nthread scaling: seconds on cpus {cpus[0]} / on cpus {cpus[-1]} (the issue asks >= 1.6 for 1 -> 2 cores)")
    for mode, name, few, many in found:
        print(f"  {mode:<16}{name:<44}{few:>8.2f}{many:>8.2f}{few / max(many, 1e-9):>7.2f}x")


def growth(rows: list[dict]) -> dict[str, dict[str, dict]]:
    """``{series: {method: {"a", "b", "points"}}}``: seconds (or GB) = a * frames^b, log-log least squares."""
    series: dict[str, dict[str, list[tuple[int, float]]]] = {}
    for r in rows:
        if "error" in r:
            continue
        values = {"wall": r["wall_s"], "cpu": r.get("cpu_s"), "peak GB": r["peak_gb"], **r["stages"]}
        values |= r.get("steps") or {}
        for name, value in values.items():
            if value is not None and value > 1e-3:  # a stage that did not run has no growth
                series.setdefault(name, {}).setdefault(r["method"], []).append((r["frames"], value))
    fits: dict[str, dict[str, dict]] = {}
    for name, by_method in series.items():
        for method, points in by_method.items():
            if len({n for n, _ in points}) < 2:
                continue
            n, t = np.log([p[0] for p in points]), np.log([p[1] for p in points])
            b, log_a = np.polyfit(n, t, 1)
            fits.setdefault(name, {})[method] = {"a": float(np.exp(log_a)), "b": float(b), "points": points}
    return fits


def print_growth(fits: dict, methods: list[str]) -> None:
    if not fits:
        print("\ngrowth: needs two frame counts or more")
        return
    print("\ngrowth: exponent b of seconds (peak GB for 'peak GB') = a * frames^b, least squares in log-log")
    print(f"{'stage':<26}" + "".join(f"{m[-22:]:>24}" for m in methods))
    for name, by_method in fits.items():
        cells = "".join(f"{by_method[m]['b']:>24.2f}" if m in by_method else f"{'-':>24}" for m in methods)
        print(f"{name:<26}{cells}")
    print("splat runs to its time budget, so its exponent reflects the budget, not its cost")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["--ffrecon-child"] and argv[2:3] == ["--"]:
        return ffrecon_child(Path(argv[1]), argv[3:])
    args = _parser().parse_args(argv)
    if args.colmap_only:
        colmap_child(*args.colmap_only, args.truth, args.colmap_pairing, args.colmap_mapping_seconds)
        return 0
    if args.prepare_only:
        _prepare_here(*args.prepare_only, args.drift)
        return 0
    if "quick" in args.modes and not quick_available():
        print("ffrecon run has no --quick option here; pass --modes default", file=sys.stderr)
        return 2
    info = machine()
    load = " ".join(f"{x:.2f}" for x in info["load_average"] or [])
    print(f"{info['cpus']} CPUs, {info['memory_gb']} GB, load average {load}; {info['platform']}")
    print(f"python {info['python']}, pycolmap {info['pycolmap']}, ffrecon {info['ffrecon']}; seed {args.seed}")
    print("seconds; xCOLMAP = wall / COLMAP-alone wall; AUC@5 and medrot (deg) vs ground truth; PSNR held-out dB")
    root = args.out or Path(tempfile.mkdtemp(prefix="ffrecon-bench-run-"))
    rows: list[dict] = []
    try:
        for frames in args.frames:
            new = bench_frames(frames, args, root)
            print_table(new)
            print_scaling(new)
            rows += new
    finally:
        if args.out is None and not args.keep:
            shutil.rmtree(root, ignore_errors=True)
    fits = growth(rows)
    print_growth(fits, list(dict.fromkeys(r["method"] for r in rows)))
    end_load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"load average {end_load:.2f} at the end" + (f"; outputs in {root}" if args.keep else ""))
    if args.json:
        saved = {"machine": info, "args": vars(args), "rows": rows, "growth": fits}
        args.json.write_text(json.dumps(saved, indent=1, default=str))
    return 0


if __name__ == "__main__":
    code = main()
    if sys.argv[1:2] == ["--ffrecon-child"]:  # it leaves as the ffrecon command does: at once, everything written
        from ffrecon.cli import leave

        leave(code)
    sys.exit(code)
