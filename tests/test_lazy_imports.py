"""Loading the pipeline (what every `ffrecon run` and `demo` does before the first stage) does not load the
splat's libraries or Open3D: a run without the splat never needs torch, numba or kornia, and Open3D loads
when the feed-forward stage first fuses points (issue 40: 'startup' was 2.5 s, mostly these)."""

from __future__ import annotations

import json
import subprocess
import sys

HEAVY = ("torch", "numba", "kornia", "open3d", "gsplat", "trimesh")


def _loaded_after(statement: str) -> list[str]:
    code = f"import json, sys\n{statement}\nprint(json.dumps(sorted(m for m in {HEAVY!r} if m in sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def test_the_pipeline_and_its_options_load_without_the_heavy_libraries():
    statement = "import ffrecon.cli, ffrecon.pipeline as p\np.RunOptions.quick(), p.RunOptions()"
    assert _loaded_after(statement) == []


def test_the_splat_stage_still_loads_them():
    """The probe sees an import: the splat stage's module loads torch and the compiled kernels."""
    assert {"torch", "numba"} <= set(_loaded_after("import ffrecon.splat.stage"))


def test_closing_a_loop_loads_no_torch():
    """The loop chunks' Sim(3) pose graph is solved in numpy: a long --quick --no-splat capture (96 frames: one
    loop call) loaded torch for it alone, 1.1 s of a run's CPU (issue 40)."""
    statement = (
        "import numpy as np\n"
        "from ffrecon.geometry.alignment import Sim3\n"
        "from ffrecon.geometry.pose_graph import Sim3Edge, optimize_pose_graph\n"
        "turn = Sim3(1.0, np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]), np.zeros(3))\n"
        "result = optimize_pose_graph([Sim3.identity()] * 2, [Sim3Edge(0, 1, turn.inverse())], 1.0)\n"
        "assert result.cost_after < 1e-20"
    )
    assert "torch" not in _loaded_after(statement)
