"""Resume: an interrupted run keeps its finished stages; --resume recomputes only what changed."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from plyfile import PlyData

import ffrecon.sfm.crosscheck.matching as crosscheck
import ffrecon.splat.final as splat_final
from ffrecon.cli import main
from ffrecon.errors import Interrupted
from ffrecon.models.multiview import MultiviewOptions
from ffrecon.models.stage import FeedForwardOptions
from ffrecon.pipeline import RunOptions, run
from ffrecon.results import Skipped
from ffrecon.sfm.crosscheck.gate_types import GateOptions
from ffrecon.splat.optimize import OptimizeOptions
from ffrecon.splat.stage import SplatOptions
from ffrecon.workspace import staging_path
from tests.conftest import ctrl_c_default

FIXED_CHUNKS = FeedForwardOptions(multiview=MultiviewOptions(chunk_size=8))
BEFORE_SPLAT = ["capture", "feedforward", "colmap_matching", "colmap", "refine", "gates", "evidence", "comparisons"]


def _options(**kw) -> RunOptions:
    """Two runs that do the same work: a splat bounded by iterations, not seconds, and a fixed chunk size
    (the default follows the memory free at run time, which differs between the runs of a long test session)."""
    splat = SplatOptions(optimize=OptimizeOptions.brief(iterations=20, max_seconds=1e6, progress=False), video=False)
    return RunOptions(splat=splat, feedforward=FIXED_CHUNKS, **kw)


def _ply(path: Path) -> dict[str, np.ndarray]:
    vertex = PlyData.read(str(path))["vertex"]
    return {name: np.asarray(vertex[name]) for name in vertex.data.dtype.names}


@pytest.fixture(scope="module")
def uninterrupted(demo12, tmp_path_factory):
    out = tmp_path_factory.mktemp("whole") / "out"
    return out, run(demo12.images, out, demo12.model, _options())


def test_interrupted_splat_resumes_with_only_the_splat_recomputed(demo12, uninterrupted, tmp_path, monkeypatch):
    whole_dir, whole = uninterrupted
    out = tmp_path / "out"
    (out / ".ffrecon").mkdir(parents=True)  # an earlier ffrecon output (its marker)
    (out / "earlier.txt").write_text("earlier results")

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(splat_final, "run_splat_from_prediction", interrupt)
        with pytest.raises(Interrupted) as caught:
            run(demo12.images, out, demo12.model, _options(overwrite=True, command="ffrecon run x"))
    err = caught.value
    assert err.stage == "splat" and err.kept == BEFORE_SPLAT and err.exit_code == 130
    assert "--resume" in err.fix
    assert sorted(p.name for p in out.iterdir()) == [".ffrecon", "earlier.txt"]  # OUT untouched
    assert (staging_path(out.resolve()) / ".ffrecon" / "stages" / "refine.json").is_file()

    resumed = run(demo12.images, out, demo12.model, _options(resume=True))
    reused = {t.stage: t.reused for t in resumed.timings}
    assert reused == {**dict.fromkeys(BEFORE_SPLAT, True), "splat": False, "exports": False}
    timings = json.loads((out / "report.json").read_text())["timings"]
    assert [s for s, t in timings.items() if t["reused"]] == BEFORE_SPLAT
    assert "reused" in (out / "report.html").read_text()

    # The same outputs as the uninterrupted run with the same seed: the cameras and clouds the splat
    # starts from, then the splat.
    assert json.loads((out / "transforms.json").read_text()) == json.loads((whole_dir / "transforms.json").read_text())
    np.testing.assert_allclose(_ply(out / "points.ply")["x"], _ply(whole_dir / "points.ply")["x"])
    ra, rb = (pycolmap.Reconstruction(str(d / "sparse" / "0")) for d in (whole_dir, out))
    assert ra.num_points3D() == rb.num_points3D()
    a, b = _ply(whole_dir / "splat.ply"), _ply(out / "splat.ply")
    assert len(a["x"]) == len(b["x"]), f"{len(a['x'])} vs {len(b['x'])} Gaussians"
    assert a.keys() == b.keys() and all(np.allclose(a[k], b[k], atol=1e-6) for k in a)
    assert resumed.splat.iterations == whole.splat.iterations == 20
    assert resumed.splat.mean("psnr_cleaned") == pytest.approx(whole.splat.mean("psnr_cleaned"), abs=1e-4)
    assert not (out / "earlier.txt").exists()  # OUT was replaced by the finished run
    # Paths in the typed results point at OUT, where the files are now.
    assert resumed.splat.ply_path == out.resolve() / "splat.ply" and resumed.splat.ply_path.is_file()
    assert resumed.refine.model_path.is_dir() and resumed.colmap.reconstruction.num_reg_images() == 12


def test_resume_recomputes_what_changed_and_drops_what_was_turned_off(demo12, uninterrupted, tmp_path):
    whole_dir, _ = uninterrupted
    out = tmp_path / "copy"
    shutil.copytree(whole_dir, out)
    changed = RunOptions(
        splat=SplatOptions(enabled=False),
        gates=GateOptions(min_registration_ratio=0.5),
        feedforward=FIXED_CHUNKS,
        resume=True,
    )
    result = run(demo12.images, out, demo12.model, changed)
    # The gates run again, and what reads them: the evidence, and the exports (the evidence picks the
    # final cameras); the splat is off. Nothing upstream is recomputed.
    assert [t.stage for t in result.timings if not t.reused] == ["gates", "evidence", "exports"]
    assert isinstance(result.splat, Skipped) and "--no-splat" in result.splat.reason
    assert not (out / "splat.ply").exists() and not (out / "renders").exists()
    # Without --resume an existing OUT is refused (exit 4).
    assert main(["run", str(demo12.images), "-o", str(out), "--model", str(demo12.model), "-q"]) == 4


def test_interrupted_cross_check_keeps_the_feedforward_stage_that_ran_beside_it(demo12, tmp_path, monkeypatch):
    """COLMAP runs in a thread beside the feed-forward stage: stopped there, the run names it and keeps the
    feed-forward stage, which the resumed run reuses; the report records the two as run side by side."""
    out = tmp_path / "out"
    no_splat = dict(splat=SplatOptions(enabled=False), feedforward=FIXED_CHUNKS)

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(crosscheck, "match_colmap", interrupt)
        with pytest.raises(Interrupted) as caught:
            run(demo12.images, out, demo12.model, RunOptions(**no_splat, command="ffrecon run x"))
    assert caught.value.stage == "colmap_matching" and caught.value.kept == ["capture", "feedforward"]
    assert not out.exists()

    resumed = run(demo12.images, out, demo12.model, RunOptions(**no_splat, resume=True))
    assert [t.stage for t in resumed.timings if t.reused] == ["capture", "feedforward"]
    assert resumed.colmap.num_registered == 12 and resumed.refine.registered.all()
    report = json.loads((out / "report.json").read_text())
    pair, mapping = report["concurrent_stages"]
    assert pair["stages"] == ["feedforward", "colmap_matching"] and pair["wall_seconds"] <= pair["sum_seconds"] + 0.05
    assert report["timings"]["colmap_matching"]["concurrent_with"] == "feedforward"
    # COLMAP's mapping and the refinement read the same matches, and run side by side too
    assert mapping["stages"] == ["colmap", "refine"] and report["timings"]["refine"]["concurrent_with"] == "colmap"


@pytest.mark.slow
def test_ctrl_c_prints_one_line_and_keeps_out(demo12, tmp_path):
    """A real SIGINT (and SIGTERM) during the splat: exit 130, one line, no stack trace, OUT untouched."""
    out = tmp_path / "out"
    (out / ".ffrecon").mkdir(parents=True)  # an earlier ffrecon output (its marker)
    (out / "earlier.txt").write_text("earlier results")
    cmd = [str(Path(sys.executable).parent / "ffrecon"), "run", str(demo12.images), "-o", str(out)]
    cmd += ["--model", str(demo12.model), "--overwrite", "--splat-seconds", "600", "-q"]
    records = staging_path(out.resolve()) / ".ffrecon" / "stages"
    for sig in (signal.SIGINT, signal.SIGTERM):
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        (records / "comparisons.json").unlink(missing_ok=True)  # its return marks the splat's start
        proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, preexec_fn=ctrl_c_default
        )
        deadline = time.monotonic() + 300
        while not (records / "comparisons.json").is_file() and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.2)
        time.sleep(2.0)  # well into the splat
        proc.send_signal(sig)
        _, stderr = proc.communicate(timeout=120)
        assert proc.returncode == 130, stderr
        lines = [line for line in stderr.splitlines() if line.strip()]
        said = [line for line in lines if line.startswith("ffrecon:")]  # earlier lines: capture warnings
        assert said == lines[-1:] and "Traceback" not in stderr and "KeyboardInterrupt" not in stderr, stderr
        assert "interrupted during splat" in said[0] and "--resume" in said[0]
        assert sorted(p.name for p in out.iterdir()) == [".ffrecon", "earlier.txt"]
