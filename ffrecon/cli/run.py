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
    from ffrecon.sfm.colmap_options import PairingMode

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


def _run_options(args: argparse.Namespace, ground_truth: Path | None = None):
    from ffrecon.capture import CaptureOptions
    from ffrecon.export.stage import ExportOptions
    from ffrecon.models.adapters import PreprocessMode
    from ffrecon.models.multiview import MultiviewOptions
    from ffrecon.models.stage import FeedForwardOptions
    from ffrecon.pipeline import RunOptions
    from ffrecon.sfm.gates import GateOptions
    from ffrecon.splat.clean import CleanOptions
    from ffrecon.splat.optimize import OptimizeOptions
    from ffrecon.splat.stage import SplatOptions

    mode = PreprocessMode(args.preprocess) if args.preprocess else None
    multiview = MultiviewOptions(mode=mode, **given(chunk_size=args.chunk_size, chunk_overlap=args.chunk_overlap))
    if getattr(args, "no_loop_chunks", False):
        multiview = dataclasses.replace(multiview, loops=dataclasses.replace(multiview.loops, enabled=False))
    capture = CaptureOptions(
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
    splat = SplatOptions(
        enabled=not args.no_splat,
        compare_seeds=args.compare_seeds,
        sog=args.sog,
        optimize=OptimizeOptions.brief(**given(max_seconds=args.splat_seconds)),
        **given(clean=args.crop_box and CleanOptions(crop_box=args.crop_box)),
    )
    preset = RunOptions.quick() if args.quick else RunOptions()  # the flags below override the preset's fields
    return dataclasses.replace(
        preset,
        capture=capture,
        feedforward=FeedForwardOptions(multiview=multiview, ray=_ray_options(args), **given(threads=args.threads)),
        colmap=_colmap_options(args, preset.colmap),
        gates=GateOptions(**given(min_registration_ratio=args.min_registration)),
        refine=dataclasses.replace(preset.refine, enabled=not args.no_refine),
        splat=splat,
        exports=ExportOptions(mesh=args.mesh),
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
    from ffrecon.pipeline import run

    if args.command == "demo":
        from ffrecon.demo import DemoOptions, prepare_demo

        options = _run_options(args)  # checked before the scene is rendered
        demo = prepare_demo(DemoOptions(scene=_scene_options(args)))
        return run(demo.images, args.out, demo.model, dataclasses.replace(options, ground_truth=demo.scene_dir))
    return run(args.input, args.out, args.model, _run_options(args))


def print_summary(results) -> None:
    """The end-of-run summary, from the same report data as report.html."""
    from ffrecon.report.build import build_report
    from ffrecon.report.html import summary_rows, wall_seconds

    report = build_report(results)
    verdict = report["verdict"]
    print(f"\nffrecon: {verdict['status'].upper()} - {verdict['message']}")
    for item, value in summary_rows(report):
        print(f"  {item:<28} {value}")
    for item in report["skipped_stages"]:
        print(f"  skipped {item['stage']}: {item['reason']}")
    print(f"  {'time':<28} {wall_seconds(report):.1f} s")
    print(f"  report: {results.out_dir / 'report.html'}")
    print(f"  look around in 3D: ffrecon view {results.out_dir}")
