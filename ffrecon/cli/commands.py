"""The commands besides ``run`` and ``demo``: ``inspect-model``, ``export-model``, ``view`` and ``render``."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from ffrecon.cli.argtypes import given
from ffrecon.cli.signals import leave_now, take_sigterm_back

log = logging.getLogger("ffrecon")


def inspect_model(path: Path) -> None:
    from ffrecon.models.adapters import adapter_for
    from ffrecon.models.runner import FAMILY_NAMES, OnnxModel
    from ffrecon.types import ModelFamily

    model = OnnxModel(path)
    simulated = " (SIMULATED)" if model.simulated else ""
    print(f"{path.name}: {FAMILY_NAMES[model.family]} ({model.family.value}) model{simulated}")
    print("inputs:\n" + "\n".join(f"  {s}" for s in model.inputs))
    print("outputs:\n" + "\n".join(f"  {s}" for s in model.outputs))
    if model.family is ModelFamily.PAIRWISE:
        print(
            "preprocessing: RGB (x/255 - 0.5) / 0.5; long side 512 (224 checkpoints: short side 224, centre "
            "square), sides cropped to multiples of 16, square photos to 4:3; pairs from a pair graph, then "
            "global alignment"
        )
        if {"desc", "desc_conf"} <= {o.name for o in model.outputs}:
            print("MASt3R descriptors (desc, desc_conf per view) are checked but not used yet")
    else:
        adapter = adapter_for(model.family)
        print(f"contract: {adapter.description}")
        print(f"preprocessing modes: {', '.join(m.value for m in adapter.modes)}; world frame: {adapter.world_frame}")
    for k, v in model.metadata.items():
        print(f"  metadata {k}: {v[:200]}")


def _export_options(args: argparse.Namespace):
    """``export-model``'s :class:`~ffrecon.models.exporting.ModelExportOptions`; the flags not given
    (None) leave the class's defaults."""
    from ffrecon.models.exporting import ModelExportOptions

    return ModelExportOptions(
        family=args.family,
        out=args.out,
        checkpoint=args.checkpoint,
        upstream=args.upstream,
        size_hw=(args.height, args.width) if args.height else None,
        photos=args.photos,
        fp16=args.fp16,
        fused_attention=args.fused_attention,
        random_init=args.random_init,
        tiny=args.tiny,
        keep_untrained_heads=args.keep_untrained_heads,
        verify=not args.skip_verify,
        variant=args.variant,
        **given(opset=args.opset, count=args.frames, seed=args.seed),
    )


def export_command(args: argparse.Namespace) -> None:
    import warnings

    from ffrecon.models.exporting import export_model

    options = _export_options(args)
    with warnings.catch_warnings():
        warnings.simplefilter(
            "ignore"
        )  # the tracer's warnings are about the Python-side size logic the export fixes on purpose
        report = export_model(options)
    print(report.summary())


def _view_options(args: argparse.Namespace):
    """``view``'s :class:`~ffrecon.view.ViewOptions`: the caps given, the class's defaults else."""
    from ffrecon.view import ViewOptions

    return ViewOptions(**given(max_points=args.max_points, max_gaussians=args.max_gaussians))


def view_command(args: argparse.Namespace) -> int:
    """Serve the viewer until Ctrl-C (or SIGTERM), then stop it and say so in one line (exit 0)."""
    import time

    from ffrecon.view import load_scene, start_viewer

    started = time.perf_counter()
    scene = load_scene(args.out, _view_options(args))
    take_sigterm_back()  # pycolmap, imported by load_scene, installs its own handler
    viewer = start_viewer(scene, **given(host=args.host, port=args.port))
    for what, why in scene.missing:
        log.info("not shown: %s (%s)", what, why)
    print(f"viewer: {viewer.url}  (ready in {time.perf_counter() - started:.1f} s; Ctrl-C stops it)", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        stopped = viewer.stop()
        print("ffrecon: viewer stopped", file=sys.stderr)
        if not stopped:  # a connection held the server: leave without waiting for its threads at exit
            leave_now(0)
    return 0


def render_command(args: argparse.Namespace) -> int:
    from ffrecon.render_path import render_path

    done = render_path(args.out, args.camera_path, args.output, overwrite=args.overwrite, device=args.device or "auto")
    if not args.quiet:
        print(done.summary())
    return 0
