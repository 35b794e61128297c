"""Typed stage records: every stage's result round-trips; a record never runs code, and one that does not
decode into today's classes (another format, a class outside ffrecon, a broken file, a pickle) is refused
and its stage runs again."""

import dataclasses
import enum
import json
import logging
import math
import pickle
import shutil
import sys
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from ffrecon.geometry.alignment import Sim3
from ffrecon.pipeline import RunOptions, run
from ffrecon.records import RecordError, decode, encode
from ffrecon.results import Skipped
from ffrecon.resume import StageRunner, rebase_paths, stage_key
from ffrecon.sfm.crosscheck.gate_types import GateStatus
from ffrecon.splat.optimize import OptimizeOptions
from ffrecon.splat.stage import SplatOptions

RECORDS = Path(".ffrecon") / "stages"


def assert_same(a, b, where: str = "result") -> None:
    """``a`` and ``b`` hold the same values of the same types (arrays: dtype, shape, values, NaN equal to NaN)."""
    assert type(a) is type(b), f"{where}: {type(a).__name__} != {type(b).__name__}"
    if isinstance(a, np.ndarray):
        assert (a.dtype, a.shape) == (b.dtype, b.shape), where
        assert np.array_equal(a, b, equal_nan=a.dtype.kind in "fc"), where
    elif dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            assert_same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, (tuple, list)):
        assert len(a) == len(b), where
        for k, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{where}[{k}]")
    elif isinstance(a, dict):
        assert list(a) == list(b), where
        for k in a:
            assert_same(a[k], b[k], f"{where}[{k!r}]")
    elif isinstance(a, pycolmap.Reconstruction):  # reloaded from the result's model_path
        assert a.summary() == b.summary(), where
    elif isinstance(a, (float, np.floating)):
        assert (a == b and math.copysign(1, a) == math.copysign(1, b)) or (np.isnan(a) and np.isnan(b)), where
    else:
        assert a == b, where


# -- the codec --------------------------------------------------------------------------------------


class Colour(enum.Enum):  # not ffrecon's: records refuse it
    RED = "red"


@dataclasses.dataclass(frozen=True)
class Outsider:  # not ffrecon's: records refuse it
    x: int


def test_values_of_every_kind_round_trip():
    value = {
        "scalars": ("text", 3, -0.0, 1e300, True, None, math.nan, math.inf, -math.inf),
        "numpy": (np.float32(0.1), np.int64(-7), np.bool_(True), np.float64("nan")),
        "arrays": [np.arange(6, dtype=np.uint8).reshape(2, 3), np.array([np.nan, 1.0], np.float32), np.zeros((0, 3))],
        5: {0.5: GateStatus.PASS, None: Skipped("splat", "turned off (--no-splat)")},
        "paths": (Path("<run>/images"), Path("/elsewhere/x.ply")),
        "nested": Sim3(2.0, np.eye(3), np.array([1.0, -2.0, 3.0])),
    }
    tree, arrays = encode(value)
    assert json.loads(json.dumps(tree, allow_nan=False)) == tree  # strict JSON
    assert_same(decode(tree, arrays), value)


@pytest.mark.parametrize(
    "value",
    [
        lambda: None,
        np.array([1, "a"], dtype=object),
        pycolmap.Reconstruction(),
        Outsider(1),
        Colour.RED,
        {"a": {1, 2}},
        np.ma.masked_array([1.0]),
    ],
    ids=["callable", "object-array", "pycolmap", "dataclass-outside-ffrecon", "enum-outside-ffrecon", "set", "masked"],
)
def test_what_is_not_data_is_not_encoded(value):
    with pytest.raises(RecordError):
        encode({"field": value})


# -- every stage of real runs -----------------------------------------------------------------------


@pytest.fixture(scope="module")
def recorded(demo12, small_demo, tmp_path_factory):
    """Every stage a run records: a full run of 12 frames with every stage (the seed comparison too) and a
    quick run of 8 (its SIFT stage). ``[(out folder, stage, key, result as the stage returned it)]``."""
    stored = []
    store = StageRunner._store

    def keep(self, stage, key, result, *args):
        stored.append((self.run_dir, stage, key, result))
        store(self, stage, key, result, *args)

    brief = OptimizeOptions.brief(iterations=10, max_seconds=1e6, progress=False)
    full = RunOptions(
        splat=SplatOptions(optimize=brief, video=False, compare_seeds=True), ground_truth=demo12.scene_dir
    )
    quick = RunOptions.quick(splat=SplatOptions(enabled=False))
    found = []
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(StageRunner, "_store", keep)
        for demo, options in ((demo12, full), (small_demo, quick)):
            out = tmp_path_factory.mktemp("records") / "out"
            run(demo.images, out, demo.model, options)
            found += [(out, stage, key, rebase_paths(result, run_dir, out)) for run_dir, stage, key, result in stored]
            stored.clear()
    return found


def test_every_stage_record_decodes_to_the_result_it_stored(recorded):
    stages = {stage for _, stage, _, _ in recorded}
    every = {
        "capture",
        "feedforward",
        "colmap_matching",
        "colmap",
        "sift",
        "gates",
        "refine",
        "evidence",
        "comparisons",
    }
    assert stages == every | {"splat", "seed_comparison", "exports"}
    for out, stage, key, result in recorded:
        folder = out / RECORDS
        assert (folder / f"{stage}.json").is_file() and not (folder / f"{stage}.pkl").exists()
        loaded = StageRunner(out, reuse=True)._load(stage, key)  # as --resume reads it from the finished OUT
        assert loaded is not None, stage
        assert_same(loaded[0], result, stage)
    assert not list(out.rglob("*.pkl"))


# -- refusals ---------------------------------------------------------------------------------------


class _Planted:
    """Unpickling this creates ``marker``: what a hostile folder's pickle would do."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return open, (str(self.marker), "w")


def _probe(run_dir: Path) -> tuple[object, int]:
    """Run the stage "probe" (a result with arrays, paths, an enum and a nested dataclass) through a new
    runner that reuses records: ``(result, 1 if it ran, 0 if its record was reused)``."""
    calls = []

    def probe():
        calls.append(1)
        return (Sim3(2.0, np.eye(3), np.arange(3.0)), run_dir / "a.ply", GateStatus.PASS, Skipped("x", "why"))

    result, _ = StageRunner(run_dir, reuse=True).run("probe", probe, options="probe options", inputs=["input"])
    return result, len(calls)


def _edit(record: Path, change) -> None:
    meta = json.loads(record.read_text())
    change(meta)
    record.write_text(json.dumps(meta))


def test_a_record_is_reused_where_the_run_folder_is_moved(tmp_path):
    first, ran = _probe(tmp_path / "run")
    assert ran == 1 and (tmp_path / "run" / RECORDS / "probe.npz").is_file()
    shutil.copytree(tmp_path / "run", tmp_path / "moved")
    moved, ran = _probe(tmp_path / "moved")
    assert ran == 0 and moved[1] == tmp_path / "moved" / "a.ply"
    assert_same(moved, rebase_paths(first, tmp_path / "run", tmp_path / "moved"))


CLASSES = {  # what constructing each would do: create the marker file (or run ffrecon's command line)
    "io:FileIO": lambda marker: {"file": str(marker), "mode": "w"},
    "subprocess:Popen": lambda marker: {"args": ["touch", str(marker)]},
    "os:system": lambda marker: {"command": f"touch {marker}"},
    "builtins:eval": lambda marker: {"source": f"open({str(marker)!r}, 'w')"},  # (eval takes no keywords)
    "pathlib:Path.touch": lambda marker: {"self": {"$path": str(marker)}},
    "ffrecon.__main__:main": lambda marker: {},
    "ffrecon.resume:shutil.copy": lambda marker: {"src": __file__, "dst": str(marker)},
    "ffrecon.resume:StageRunner": lambda marker: {"run_dir": str(marker), "reuse": True},
}


@pytest.mark.parametrize("name", CLASSES)
@pytest.mark.parametrize("tag", ["$dataclass", "$enum"])
def test_a_record_naming_a_class_outside_ffrecons_data_is_refused_and_runs_nothing(name, tag, tmp_path, caplog):
    run_dir, marker = tmp_path / "run", tmp_path / "marker"
    _probe(run_dir)
    node = {tag: name, **CLASSES[name](marker)} if tag == "$dataclass" else {tag: name, "name": "RED"}
    _edit(run_dir / RECORDS / "probe.json", lambda meta: meta["result"]["$tuple"].__setitem__(0, node))
    with caplog.at_level(logging.INFO, logger="ffrecon"):
        _, ran = _probe(run_dir)
    assert ran == 1 and not marker.exists() and "ffrecon.__main__" not in sys.modules
    assert "the record of stage probe cannot be used" in caplog.text and name in caplog.text


def test_a_planted_pickle_is_never_unpickled_and_the_stage_runs_again(tmp_path, caplog):
    run_dir, marker = tmp_path / "run", tmp_path / "marker"
    folder = run_dir / RECORDS
    folder.mkdir(parents=True)
    (folder / "probe.pkl").write_bytes(pickle.dumps(_Planted(marker)))
    key = stage_key("probe", "probe options", ["input"])  # the record an earlier version wrote beside it
    (folder / "probe.json").write_text(json.dumps({"stage": "probe", "key": key, "seconds": 1.0}))
    with caplog.at_level(logging.INFO, logger="ffrecon"):
        _, ran = _probe(run_dir)
    assert ran == 1 and not marker.exists() and not (folder / "probe.pkl").exists()
    assert "written by another version of ffrecon (a pickled result, which is never read" in caplog.text
    assert json.loads((folder / "probe.json").read_text())["format"] == 1


def test_a_resumed_run_never_unpickles_a_planted_pickle(small_demo, tmp_path):
    out, marker = tmp_path / "out", tmp_path / "marker"
    options = RunOptions(splat=SplatOptions(enabled=False))
    run(small_demo.images, out, small_demo.model, options)
    folder = out / RECORDS
    assert not list(folder.glob("*.pkl")) and (folder / "feedforward.npz").is_file()
    meta = json.loads((folder / "capture.json").read_text())
    old = {k: meta[k] for k in ("stage", "key", "seconds", "ffrecon_version", "options", "inputs")}
    (folder / "capture.json").write_text(json.dumps(old))  # as an earlier, pickling version wrote it
    (folder / "capture.pkl").write_bytes(pickle.dumps(_Planted(marker)))
    resumed = run(small_demo.images, out, small_demo.model, dataclasses.replace(options, resume=True))
    reused = {t.stage: t.reused for t in resumed.timings}
    assert not marker.exists() and reused.pop("capture") is False and all(reused.values())
    assert not (folder / "capture.pkl").exists() and json.loads((folder / "capture.json").read_text())["format"] == 1


def _npz_with_pickle(folder: Path, marker: Path) -> None:
    with open(folder / "probe.npz", "wb") as fh:
        np.savez(fh, a0=np.array([_Planted(marker)], dtype=object), a1=np.zeros(3))


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _field(meta: dict, old: str, new: str) -> None:
    sim = meta["result"]["$tuple"][0]
    sim[new] = sim.pop(old)


TAMPERED = {  # how a record is broken, and what the log says
    "other format": (lambda f, m: _edit(f / "probe.json", lambda meta: meta.update(format=2)), "record format 2"),
    "truncated json": (lambda f, m: _truncate(f / "probe.json"), "not valid JSON"),
    "json list": (lambda f, m: (f / "probe.json").write_text("[]"), "not a record"),
    "json NaN": (
        lambda f, m: _edit(f / "probe.json", lambda meta: meta["result"]["$tuple"][0].update(scale=math.nan)),
        "NaN",
    ),
    "truncated npz": (lambda f, m: _truncate(f / "probe.npz"), "probe.npz"),
    "garbage npz": (lambda f, m: (f / "probe.npz").write_bytes(b"\x00" * 100), "probe.npz"),
    "missing npz": (lambda f, m: (f / "probe.npz").unlink(), "holds no array 'a0'"),
    "pickled array": (_npz_with_pickle, "allow_pickle"),
    "renamed field": (
        lambda f, m: _edit(f / "probe.json", lambda meta: _field(meta, "scale", "s")),
        "other fields now",
    ),
    "array shape": (
        lambda f, m: _edit(f / "probe.json", lambda meta: meta["result"]["$tuple"][0]["rotation"].update(shape=[9])),
        "the record says <f8 [9]",
    ),
    "enum member": (
        lambda f, m: _edit(f / "probe.json", lambda meta: meta["result"]["$tuple"][2].update(name="GONE")),
        "GONE",
    ),
    "two tags": (
        lambda f, m: _edit(f / "probe.json", lambda meta: meta["result"].update({"$path": "x"})),
        "one '$' tag",
    ),
}


@pytest.mark.parametrize("case", TAMPERED)
def test_a_broken_or_foreign_record_is_refused_and_the_stage_runs_again(case, tmp_path, caplog):
    run_dir, marker = tmp_path / "run", tmp_path / "marker"
    first, _ = _probe(run_dir)
    tamper, said = TAMPERED[case]
    tamper(run_dir / RECORDS, marker)
    with caplog.at_level(logging.INFO, logger="ffrecon"):
        again, ran = _probe(run_dir)
    assert ran == 1 and not marker.exists()
    assert "running it again" in caplog.text and said in caplog.text
    assert_same(again, first)
    _, ran = _probe(run_dir)  # recorded afresh
    assert ran == 0


def test_a_result_that_is_not_data_runs_again_instead_of_failing_the_run(tmp_path, caplog):
    runner = StageRunner(tmp_path, reuse=True)
    with caplog.at_level(logging.WARNING, logger="ffrecon"):
        result, _ = runner.run("odd", lambda: {"fn": print}, options=None, inputs=[])
    assert result == {"fn": print} and "cannot be recorded" in caplog.text
    assert not (tmp_path / RECORDS / "odd.json").exists()


def test_forget_removes_the_record_its_arrays_and_an_old_pickle(tmp_path):
    _probe(tmp_path)
    (tmp_path / RECORDS / "probe.pkl").write_bytes(b"old")
    StageRunner(tmp_path, reuse=True).forget("probe")
    assert not list((tmp_path / RECORDS).iterdir())
