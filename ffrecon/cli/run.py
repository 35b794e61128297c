"""``run`` and ``demo``: the command line's options as :class:`~ffrecon.options.RunOptions`, the run, its summary."""

from __future__ import annotations

import argparse
import dataclasses
import shlex
import sys
from pathlib import Path

from ffrecon.cli.argtypes import given
from ffrecon.cli.parser import DEMO_SCENE_FLAGS


def _colmap_options(args: argparse.Namespace, preset):
    from ffrecon.sfm.crosscheck.options import PairingMode

    return dataclasses.replace(
        preset,
        enabled=preset.enabled and not args.no_colmap,
        **given(
            pairing=None if args.pairing is None else PairingMode(args.pairing),
            vocab_tree_path=args.vocab_tree,
        ),
    )


def _ray_options(args: argparse.Namespace):
    from ffrecon.models.distributed import RayOptions

    if args.ray is None:  # --ray-workers and --ray-gpus need --ray (OPTION_NEEDS)
        return None
    return RayOptions(address=args.ray or None, **given(workers=args.ray_workers, gpus_per_worker=args.ray_gpus))


def _capture_options(args: argparse.Namespace, preset):
    """The preset's :class:`~ffrecon.capture.CaptureOptions` with the capture flags given laid over it."""
    return dataclasses.replace(
        preset,
        **given(
            video_frames=getattr(args, "video_frames", None),
            skip_bad_images=getattr(args, "skip_bad_images", None),
            max_image_size=args.max_image_size,
            intrinsics=args.intrinsics,
            masks=args.masks,
            poses=args.poses,
        ),
        poses_prior=args.poses_prior,
        intrinsics_prior=args.intrinsics_prior,
    )


def _feedforward_options(args: argparse.Namespace, preset):
    """The preset's :class:`~ffrecon.models.stage.FeedForwardOptions` with the model-call flags laid over it."""
    from ffrecon.models.adapters import PreprocessMode

    mode = PreprocessMode(args.preprocess) if args.preprocess else None
    multiview = dataclasses.replace(
        preset.multiview, mode=mode, **given(chunk_size=args.chunk_size, chunk_overlap=args.chunk_overlap)
    )
    if getattr(args, "no_loop_chunks", False):
        multiview = dataclasses.replace(multiview, loops=dataclasses.replace(multiview.loops, enabled=False))
    return dataclasses.replace(preset, multiview=multiview, ray=_ray_options(args), **given(threads=args.threads))


def _splat_options(args: argparse.Namespace, preset):
    """The preset's :class:`~ffrecon.splat.stage.SplatOptions` with the splat flags laid over it."""
    clean = args.crop_box and dataclasses.replace(preset.clean, crop_box=args.crop_box)
    return dataclasses.replace(
        preset,
        enabled=not args.no_splat,
        compare_seeds=args.compare_seeds,
        sog=args.sog,
        optimize=dataclasses.replace(preset.optimize, **given(max_seconds=args.splat_seconds)),
        **given(clean=clean or None),
    )


def _run_options(args: argparse.Namespace, ground_truth: Path | None = None):
    """The run's options: the preset (``--quick``'s or the full run's) with every flag given laid over its field."""
    from ffrecon.pipeline import RunOptions

    preset = RunOptions.quick() if args.quick else RunOptions()
    return dataclasses.replace(
        preset,
        capture=_capture_options(args, preset.capture),
        feedforward=_feedforward_options(args, preset.feedforward),
        colmap=_colmap_options(args, preset.colmap),
        gates=dataclasses.replace(preset.gates, **given(min_registration_ratio=args.min_registration)),
        refine=dataclasses.replace(preset.refine, enabled=not args.no_refine),
        splat=_splat_options(args, preset.splat),
        exports=dataclasses.replace(preset.exports, mesh=args.mesh),
        overwrite=args.overwrite,
        resume=args.resume,
        fresh=args.fresh,
        force=args.force,
        ground_truth=ground_truth,
        reference=args.reference,
        command=shlex.join(["ffrecon", *sys.argv[1:]]),
    )


def _scene_options(args: argparse.Namespace):
    """The demo scene's :class:`~ffrecon.synthetic.SceneOptions`: the flags given, the class's defaults else."""
    from ffrecon.synthetic import SceneOptions

    return SceneOptions(**given(**{name: getattr(args, dest) for dest, name, *_ in DEMO_SCENE_FLAGS}))


def _run_command(args: argparse.Namespace):
    """``run`` or ``demo``; ``args.started`` (when set): the :class:`~ffrecon.timing.Clock` that the run's
    "startup" is timed from."""
    from ffrecon.pipeline import run

    started = getattr(args, "started", None)
    if args.command == "demo":
        from ffrecon.demo import DemoOptions, prepare_demo

        options = _run_options(args)  # checked before the scene is rendered
        demo = prepare_demo(DemoOptions(scene=_scene_options(args)))
        options = dataclasses.replace(options, ground_truth=demo.scene_dir)
        return run(demo.images, args.out, demo.model, options, started=started)
    return run(args.input, args.out, args.model, _run_options(args), started=started)


def _report(results) -> dict:
    """The report.json the run wrote (built again where there is none)."""
    import json

    from ffrecon.report.build import build_report

    try:
        return json.loads((results.out_dir / "report.json").read_text())
    except (OSError, ValueError):
        return build_report(results)


def _verdict_line(report: dict) -> str:
    verdict = report["verdict"]
    return f"ffrecon: {verdict['status'].upper()} - {verdict['message']}"


def print_verdict(results) -> None:
    """The run's verdict as one line on stderr: with ``--quiet`` a run that ends with a non-zero exit code still
    says why (a gate's own log line may name a witness's failure, not the one that stopped the run)."""
    print(_verdict_line(_report(results)), file=sys.stderr)


def print_summary(results) -> None:
    """The end-of-run summary, from the report.json the run wrote (built again where there is none)."""
    from ffrecon.report.html import summary_rows, wall_seconds

    report = _report(results)
    print(f"\n{_verdict_line(report)}")
    for item, value in summary_rows(report):
        print(f"  {item:<28} {value}")
    for item in report["skipped_stages"]:
        print(f"  skipped {item['stage']}: {item['reason']}")
    print(f"  {'time':<28} {wall_seconds(report):.1f} s")
    print(f"  report: {results.out_dir / 'report.html'}")
    print(f"  look around in 3D: ffrecon view {results.out_dir}")
