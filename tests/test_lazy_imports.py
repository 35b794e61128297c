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
