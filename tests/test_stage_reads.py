"""A stage reads the run state only through a view of what it declared (issue 41): reading anything else fails,
so a stage's resume key (made of its declared reads) cannot go stale.

The views are what every run uses, so a run that ends proves the reads it took are declared; the runs here take
every stage's run and skip rules at least once (model or none, full or quick mode, the splat and the seed
comparison) and check that they did."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from ffrecon.pipeline import RunOptions, run
from ffrecon.sfm.crosscheck.options import ColmapOptions
from ffrecon.sfm.refine.options import RefineOptions
from ffrecon.splat.optimize import OptimizeOptions
from ffrecon.splat.stage import SplatOptions
from ffrecon.stages import GATES, STAGES
from ffrecon.state import Beside, RunState, StateView, UndeclaredRead, each_stage
from ffrecon.types import RunMode, Skipped

FF_ONLY = dict(
    colmap=ColmapOptions(enabled=False), refine=RefineOptions(enabled=False), splat=SplatOptions(enabled=False)
)


def test_a_view_shows_the_inputs_and_the_declared_results_only():
    state = RunState(Path("photos"), None, Path("work"), {"colmap": "colmap's", "gates": Skipped("gates", "why")})
    view = StateView(state, "refine", ("colmap", "sift"))
    assert (view.source, view.model, view.work) == (Path("photos"), None, Path("work"))
    assert view.colmap == view["colmap"] == "colmap's" and view.sift is None  # declared, not run yet
    with pytest.raises(UndeclaredRead, match=r"stage 'refine' read 'gates'.*add 'gates' to the Stage's reads"):
        view.gates
    with pytest.raises(UndeclaredRead, match="read 'tiny'"):
        view["tiny"]
    # A derived property reads through the view too: the verdicts read the gates and the evidence.
    with pytest.raises(UndeclaredRead, match="read 'gates'"):
        view.verdicts
    assert state.gates.reason == "why" and state.verdicts == (state.gates, None)  # the whole state reads all


def _recording(steps, took: dict[str, set[str]]):
    """The stage list with each stage's run and skip rule noting, in ``took``, that they were called."""

    def note(stage, what, fn):
        def wrapped(*args):
            took.setdefault(stage.name, set()).add(what)
            return fn(*args)

        return wrapped

    def wrap(stage):
        return dataclasses.replace(stage, run=note(stage, "run", stage.run), skip=note(stage, "skip", stage.skip))

    return tuple(Beside(tuple(map(wrap, s.stages))) if isinstance(s, Beside) else wrap(s) for s in steps)


def test_every_stage_reads_only_what_it_declares(small_demo, demo12, tmp_path):
    """Each run raises :class:`UndeclaredRead` at the first undeclared read; between them they run every stage
    and its skip rule (12-15 s on 2 shared cores: the 12-frame scene with a 10-iteration splat and the seed
    comparison, then 8 frames in quick mode and without a model)."""
    took: dict[str, set[str]] = {}
    stages = _recording(STAGES, took)
    splat = SplatOptions(
        optimize=OptimizeOptions.brief(iterations=10, max_seconds=1e6, progress=False), video=False, compare_seeds=True
    )
    runs = {
        "full": (demo12, demo12.model, RunOptions(splat=splat, ground_truth=demo12.scene_dir)),
        "quick": (small_demo, small_demo.model, RunOptions(mode=RunMode.QUICK, splat=SplatOptions(enabled=False))),
        "no model": (small_demo, None, RunOptions(splat=SplatOptions(enabled=False))),
    }
    ran = {}
    for name, (demo, model, options) in runs.items():
        result = run(demo.images, tmp_path / name.replace(" ", "_"), model, options, stages=stages)
        ran[name] = {s.name for s in each_stage(STAGES) if not isinstance(result[s.name], Skipped | None)}
    assert ran["full"] == {s.name for s in each_stage(STAGES)} - {"sift"}  # all but quick mode's SIFT
    assert "sift" in ran["quick"] and "feedforward" not in ran["no model"]
    assert all(took[s.name] == {"run", "skip"} for s in each_stage(STAGES)), took


def test_a_stage_that_reads_what_it_did_not_declare_stops_the_run(small_demo, tmp_path):
    """The gates read COLMAP's result: declared without it, the run stops at the gates' first read of it."""
    undeclared = dataclasses.replace(GATES, reads=tuple(r for r in GATES.reads if r != "colmap"))
    stages = tuple(undeclared if s is GATES else s for s in STAGES)
    with pytest.raises(UndeclaredRead, match="stage 'gates' read 'colmap'"):
        run(small_demo.images, tmp_path / "out", small_demo.model, RunOptions(**FF_ONLY), stages=stages)
