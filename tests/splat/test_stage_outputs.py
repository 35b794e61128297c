"""The splat stage's files are all declared (a resumed run removes what it declared before the stage runs again), and
the stage renders and scores in one place (issue 41)."""

import ast
from pathlib import Path

from ffrecon.formats.camera_path import CAMERA_PATH_FILE
from ffrecon.splat import stage
from ffrecon.splat.optimize import OptimizeOptions
from ffrecon.splat.stage import OUTPUTS, SplatOptions, run_splat
from tests.splat.conftest import seeded_scene

_STAGE_MODULES = ("stage", "evaluate", "stage_run", "outputs", "options", "result")


def test_every_file_the_stage_writes_is_declared(tmp_path):
    scene, xyz, rgb = seeded_scene(48, 32)
    options = SplatOptions(
        max_seed_points=500,
        video_frames=2,
        device="cpu",
        curve_every=0,
        optimize=OptimizeOptions.brief(iterations=3, max_seconds=1e9, progress=False, sh_degree=0, threads=1),
    )
    cameras = [scene.camera] * len(scene)
    run_splat(list(scene.images), scene.names, scene.cam_from_world, cameras, xyz, rgb, options, tmp_path)
    written = {p.name for p in tmp_path.iterdir()}
    assert CAMERA_PATH_FILE in written and "flythrough.mp4" in written
    assert written <= set(OUTPUTS), f"written but not in OUTPUTS: {written - set(OUTPUTS)}"


def _calls(module: str) -> dict[str, set[str]]:
    """Function name -> the names it calls, in ffrecon/splat/<module>.py."""
    tree = ast.parse((Path(stage.__file__).parent / f"{module}.py").read_text())
    calls = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef):
            calls[f"{module}.{node.name}"] = {
                c.func.id if isinstance(c.func, ast.Name) else getattr(c.func, "attr", "")
                for c in ast.walk(node)
                if isinstance(c, ast.Call)
            }
    return calls


def test_the_stage_renders_in_one_place():
    """Only evaluate.render_view calls the renderer, and only evaluate.render_and_score renders and then scores:
    the held-out curve, the cleaning's judge, the probe, the pose check and the final scores go through it."""
    calls = {name: called for module in _STAGE_MODULES for name, called in _calls(module).items()}
    assert [name for name, called in calls.items() if "render_view_on" in called] == ["evaluate.render_view"]
    both = [name for name, called in calls.items() if "render_view" in called and "image_metrics" in called]
    assert both == ["evaluate.render_and_score"]
    users = {name for name, called in calls.items() if "render_and_score" in called}
    assert {"evaluate.score", "evaluate.probe_costs", "evaluate.judge", "evaluate.pose_changes"} <= users
    assert "evaluate._heldout_view" in users  # the final scores
