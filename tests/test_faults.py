"""Faults around the output folder: each case of the hostile-user table in the issue "Nothing lost, nothing
half-written" as a test. Every case ends with a documented exit code, one clear line, no traceback, no
user file lost and no stray folder.

Filesystem faults use real filesystems: a tmpfs mounted read-only, a small tmpfs that fills up, a tmpfs
as a mount point. They need root (or CAP_SYS_ADMIN) and are skipped with the reason where mounting is
not allowed.
"""

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import ffrecon.folders as folders
import ffrecon.workspace as workspace
from ffrecon.cli import main
from ffrecon.errors import OutputExistsError
from ffrecon.workspace import MARKER, retired_path, staging_path

FAST = ["--no-colmap", "--no-refine", "--no-splat", "-q"]  # the model's cameras alone: seconds


def _tree(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` with its bytes (what must not change)."""
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _said(capsys) -> list[str]:
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    return [line for line in err.splitlines() if line.startswith("ffrecon:")]


def _siblings(folder: Path) -> list[str]:
    """Hidden folders ffrecon could have left beside ``folder``."""
    return sorted(p.name for p in folder.parent.iterdir() if p.name.startswith("."))


def _complete(out: Path) -> bool:
    record = json.loads((out / MARKER / "output.json").read_text())
    return record["state"] == "complete" and all((out / f).exists() for f in record["files"])


@pytest.fixture
def photos(small_demo, tmp_path) -> Path:
    """A copy of the 8 demo photos that a test may place anywhere."""
    folder = tmp_path / "photos"
    shutil.copytree(small_demo.images, folder)
    return folder


# --- never delete what ffrecon did not write --------------------------------------------------------


def test_output_equal_to_the_input_is_refused_and_the_photos_stay(photos, small_demo, capsys):
    before = _tree(photos)
    for flags in (["--resume"], ["--overwrite"], []):
        assert main(["run", str(photos), "-o", str(photos), "--model", str(small_demo.model), *FAST, *flags]) == 4
        said = _said(capsys)
        assert len(said) == 1 and "is the input itself" in said[0]
    assert _tree(photos) == before and _siblings(photos) == []


def test_output_around_or_inside_the_input_is_refused(photos, small_demo, tmp_path, capsys):
    parent = photos.parent
    (parent / "notes.txt").write_text("the user's own file")
    before = _tree(parent)
    assert main(["run", str(photos), "-o", str(parent), "--model", str(small_demo.model), "--overwrite", *FAST]) == 4
    assert "contains the input" in _said(capsys)[0]
    assert main(["run", str(photos), "-o", str(photos / "out"), "--model", str(small_demo.model), *FAST]) == 4
    assert "lies inside the input" in _said(capsys)[0]
    assert _tree(parent) == before and not (photos / "out").exists()


@pytest.mark.parametrize("flag", ["--overwrite", "--resume", None])
def test_a_folder_ffrecon_did_not_write_is_never_touched(photos, small_demo, tmp_path, capsys, flag):
    out = tmp_path / "mine"
    (out / "sub").mkdir(parents=True)
    (out / "thesis.tex").write_text("months of work")
    (out / "sub" / "data.csv").write_text("1,2,3")
    before = _tree(out)
    args = ["run", str(photos), "-o", str(out), "--model", str(small_demo.model), *FAST] + ([flag] if flag else [])
    assert main(args) == 4
    said = _said(capsys)
    assert len(said) == 1 and "ffrecon did not write" in said[0] and "whatever the flags" in said[0]
    assert _tree(out) == before and _siblings(out) == []


def test_an_existing_file_as_output_is_refused_and_later_runs_work(photos, small_demo, tmp_path, capsys):
    target = tmp_path / "results.txt"
    target.write_text("not a folder")
    assert main(["run", str(photos), "-o", str(target), "--model", str(small_demo.model), "--overwrite", *FAST]) == 4
    assert "is a file, not a folder" in _said(capsys)[0]
    assert target.read_text() == "not a folder" and _siblings(target) == []
    out = tmp_path / "out"
    assert main(["run", str(photos), "-o", str(out), "--model", str(small_demo.model), *FAST]) == 0
    assert _complete(out)


def test_overwrite_keeps_files_a_person_added_to_an_earlier_output(photos, small_demo, tmp_path):
    out = tmp_path / "out"
    assert main(["run", str(photos), "-o", str(out), "--model", str(small_demo.model), *FAST]) == 0
    (out / "my_notes.txt").write_text("the user's notes")
    (out / "images" / "favourite.txt").write_text("a file inside an ffrecon folder")
    assert main(["run", str(photos), "-o", str(out), "--model", str(small_demo.model), "--overwrite", *FAST]) == 0
    assert (out / "my_notes.txt").read_text() == "the user's notes"
    assert (out / "images" / "favourite.txt").read_text() == "a file inside an ffrecon folder"
    assert _complete(out) and _siblings(out) == []
    # and the next replacement still knows them as the user's (they are not in ffrecon's list)
    assert main(["run", str(photos), "-o", str(out), "--model", str(small_demo.model), "--overwrite", *FAST]) == 0
    assert (out / "my_notes.txt").exists() and (out / "images" / "favourite.txt").exists()


def test_resume_copies_only_what_ffrecon_wrote(photos, small_demo, tmp_path):
    out = tmp_path / "out"
    assert main(["run", str(photos), "-o", str(out), "--model", str(small_demo.model), *FAST]) == 0
    (out / "my_notes.txt").write_text("notes")
    assert main(["run", str(photos), "-o", str(out), "--model", str(small_demo.model), "--resume", *FAST]) == 0
    record = json.loads((out / MARKER / "output.json").read_text())
    assert "my_notes.txt" not in record["files"] and (out / "my_notes.txt").read_text() == "notes"


def test_a_failed_gate_does_not_replace_earlier_good_results(demo12, small_demo, tmp_path, capsys):
    """A run whose gate fails (8 photos COLMAP cannot register, and no model to carry them) into a folder
    holding a good run (12 photos): the good results stay; the rejected run is kept aside, named, for
    --force --resume."""
    out = tmp_path / "out"
    good = ["run", str(demo12.images), "-o", str(out), "--model", str(demo12.model), "--no-splat", "-q"]
    assert main(good) == 0
    before = _tree(out)
    capsys.readouterr()
    bad = ["run", str(small_demo.images), "-o", str(out), "--no-splat"]
    assert main([*bad, "--overwrite"]) == 5
    err = capsys.readouterr().err
    assert "Traceback" not in err and "the earlier results in" in err and "--force --resume" in err
    assert _tree(out) == before
    rejected = staging_path(out)
    report = json.loads((rejected / "report.json").read_text())
    assert report["verdict"]["status"] == "gate_failed"
    assert json.loads((rejected / MARKER / "output.json").read_text())["state"] == "rejected"
    # Asked for explicitly: --force takes the rejected run's finished stages and replaces OUT.
    assert main([*bad, "--resume", "--force", "-q"]) == 0
    assert _complete(out) and not rejected.exists()
    assert json.loads((out / "report.json").read_text())["inputs"]["num_frames"] == 8


# --- failed starts leave nothing ----------------------------------------------------------------------


def test_input_and_model_errors_leave_no_staging_folder(photos, small_demo, tmp_path, capsys):
    out = tmp_path / "out"
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")
    cases = [
        (["run", str(tmp_path / "nowhere"), "-o", str(out), *FAST], 2),
        (["run", str(photos), "-o", str(out), "--model", str(junk), *FAST], 3),
        (["run", str(photos), "-o", str(out), "--model", str(tmp_path / "missing.onnx"), *FAST], 2),
    ]
    for args, code in cases * 3:  # repeated: nothing piles up
        assert main(args) == code
        assert len(_said(capsys)) == 1
    assert not out.exists() and _siblings(out) == []


def test_a_missing_parent_made_for_a_failed_run_is_removed(tmp_path, capsys):
    out = tmp_path / "new" / "deeper" / "out"
    assert main(["run", str(tmp_path / "nowhere"), "-o", str(out), *FAST]) == 2
    assert not (tmp_path / "new").exists()


# --- one run per output folder ------------------------------------------------------------------------


def _cli(args: list[str]) -> subprocess.Popen:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen(
        [sys.executable, "-m", "ffrecon", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
    )


def test_two_runs_on_one_folder_give_one_result_and_one_clear_refusal(demo12, tmp_path):
    out = tmp_path / "out"
    args = ["run", str(demo12.images), "-o", str(out), "--model", str(demo12.model), "--no-splat", "-q"]
    first = _cli(args)
    lock = staging_path(out) / MARKER / "run.json"
    deadline = time.monotonic() + 120
    while not lock.exists() and first.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    second = _cli(args)
    _, err2 = second.communicate(timeout=300)
    _, err1 = first.communicate(timeout=300)
    assert first.returncode == 0, err1
    assert second.returncode == 4, err2
    said = [line for line in err2.splitlines() if line.startswith("ffrecon:")]
    assert len(said) == 1 and f"process {first.pid}" in said[0] and "Traceback" not in err2
    assert _complete(out) and _siblings(out) == []
    report = json.loads((out / "report.json").read_text())
    assert all((out / name).exists() for name in ("images", "crosscheck", "colmap", "sparse", "report.html"))
    assert report["verdict"]["status"] == "ok"


@pytest.mark.parametrize("after_s", [0.25, 0.5, 0.8, 1.2, 2.0])
def test_sigterm_while_starting_up_ends_in_one_line(demo12, tmp_path, after_s):
    """SIGTERM during the imports (pycolmap installs glog's stack-dumping handler; a signal inside a C
    extension's initialisation becomes an ImportError): exit 130 with one line, never a stack dump. Before
    main() runs (the interpreter's first ~0.15 s) Python's default applies: a silent exit by SIGTERM."""
    out = tmp_path / "out"
    proc = _cli(["run", str(demo12.images), "-o", str(out), "--model", str(demo12.model), "--no-splat", "-q"])
    time.sleep(after_s)
    proc.terminate()
    _, err = proc.communicate(timeout=300)
    assert "Traceback" not in err and "Aborted" not in err and "stack trace" not in err, err
    assert proc.returncode in (0, 130) or (proc.returncode == -15 and not err.strip()), (proc.returncode, err)
    assert not out.exists() or _complete(out) or not any(out.iterdir())


# --- crash recovery of the swap ------------------------------------------------------------------------


def _fake_output(folder: Path, files: dict[str, str], *, listed: list[str], state: str = "complete") -> None:
    for rel, text in files.items():
        (folder / rel).parent.mkdir(parents=True, exist_ok=True)
        (folder / rel).write_text(text)
    (folder / MARKER).mkdir(parents=True, exist_ok=True)
    record = {"format": 1, "state": state, "verdict": "ok", "files": listed}
    (folder / MARKER / "output.json").write_text(json.dumps(record))


def test_a_kill_between_exchange_and_cleanup_is_recovered(tmp_path, photos):
    """Killed right after the atomic exchange: OUT is the new result; the old one (with the user's file)
    sits at the staging path. The next run moves the user's file into OUT and clears the old result."""
    out, stage = tmp_path / "out", staging_path(tmp_path / "out")
    _fake_output(out, {"report.json": "new"}, listed=["report.json"])
    _fake_output(stage, {"report.json": "old", "notes.txt": "user"}, listed=["report.json"])
    with workspace.staged_output(out, photos, overwrite=False, resume=True) as staging:
        assert not staging.finished_stages()
        staging.keep_earlier = True  # leave OUT as it is for this check
    assert (out / "report.json").read_text() == "new" and (out / "notes.txt").read_text() == "user"


def test_a_kill_between_two_renames_brings_the_earlier_results_back(tmp_path, photos):
    out = tmp_path / "out"
    _fake_output(retired_path(out), {"report.json": "old"}, listed=["report.json"])
    with workspace.staged_output(out, photos, overwrite=False, resume=True) as staging:
        staging.keep_earlier = True
    assert (out / "report.json").read_text() == "old" and not retired_path(out).exists()


class _Killed(BaseException):
    """Stands for SIGKILL: nothing after it runs (not an Exception, so no handler catches it)."""


def test_a_kill_while_deleting_replaced_results_is_finished_by_the_next_run(tmp_path, photos, monkeypatch):
    """Killed part-way through deleting the replaced results (``.OUT.old``; the soak test met this once, and the
    next run's swap failed with a traceback), after each number of deletions: the next run finishes deleting
    them and swaps its results in, and the person's file in the old results reaches OUT."""
    names = ("report.json", "report.html", "transforms.json", "points.ply", "splat.ply", "sparse/0/cameras.bin")
    files = {name: name for name in names}
    deletions = len(names) + 2 + 2 + 1  # the files, sparse/0 and sparse, the marker's record and folder, the folder
    real_unlink, real_rmdir = os.unlink, os.rmdir
    for allowed in range(deletions):
        out = tmp_path / f"out{allowed}"
        _fake_output(out, {"report.json": "older"}, listed=["report.json"])
        _fake_output(retired_path(out), files | {"mine.txt": "user"}, listed=sorted(files))
        count = [0]

        def dying(real, count=count, allowed=allowed):
            def call(*args, **kwargs):
                if count[0] >= allowed:
                    raise _Killed
                count[0] += 1
                return real(*args, **kwargs)

            return call

        with monkeypatch.context() as patch:
            patch.setattr(os, "unlink", dying(real_unlink))
            patch.setattr(os, "rmdir", dying(real_rmdir))
            with pytest.raises(_Killed):
                folders.retire(retired_path(out), out)
        left = retired_path(out)
        assert (left / MARKER).is_dir() or not any(left.iterdir()), f"after {allowed}: the marker must go last"
        with workspace.staged_output(out, photos, overwrite=True) as staging:
            _fake_output(staging.path, {"report.json": "new"}, listed=[])
        assert (out / "report.json").read_text() == "new" and (out / "mine.txt").read_text() == "user", allowed
        assert not retired_path(out).exists() and not staging_path(out).exists(), allowed


def test_a_folder_of_someone_else_where_old_results_go_is_refused_up_front(tmp_path, photos, capsys):
    out = tmp_path / "out"
    _fake_output(out, {"report.json": "older"}, listed=["report.json"])
    (retired_path(out) / "sub").mkdir(parents=True)
    (retired_path(out) / "sub" / "theirs.txt").write_text("not ffrecon's")
    with pytest.raises(OutputExistsError, match="is in the way"):
        with workspace.staged_output(out, photos, overwrite=True):
            pytest.fail("the run must be refused before it starts")
    assert (retired_path(out) / "sub" / "theirs.txt").read_text() == "not ffrecon's"
    assert (out / "report.json").read_text() == "older" and not staging_path(out).exists()


# --- filesystem faults --------------------------------------------------------------------------------


@pytest.fixture
def mount(tmp_path):
    """``mount(size, read_only)``: a fresh tmpfs under tmp_path; skipped where mounting is not allowed."""
    made = []

    def make(size: str = "1g", read_only: bool = False) -> Path:  # tmpfs takes only what is written
        point = tmp_path / f"mnt{len(made)}"
        point.mkdir()
        options = f"size={size}" + (",ro" if read_only else "")
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(point)], capture_output=True)
        if done.returncode != 0:
            point.rmdir()
            pytest.skip(f"cannot mount a tmpfs here ({done.stderr.decode().strip()}): needs root or CAP_SYS_ADMIN")
        made.append(point)
        return point

    yield make
    for point in made:
        subprocess.run(["umount", "-l", str(point)], capture_output=True)


def test_read_only_output_is_exit_6_with_one_line(photos, small_demo, mount, capsys):
    disk = mount(read_only=True)
    assert main(["run", str(photos), "-o", str(disk / "out"), "--model", str(small_demo.model), *FAST]) == 6
    said = _said(capsys)
    assert len(said) == 1 and "read-only" in said[0]


def test_a_full_disk_is_refused_up_front_and_left_as_found(photos, small_demo, mount, capsys):
    disk = mount(size="2m")
    free = shutil.disk_usage(disk).free
    assert main(["run", str(photos), "-o", str(disk / "out"), "--model", str(small_demo.model), *FAST]) == 6
    said = _said(capsys)
    assert len(said) == 1 and "MB are free" in said[0]
    assert list(disk.iterdir()) == [] and shutil.disk_usage(disk).free == free


def test_a_disk_that_fills_during_the_run_is_freed_again(photos, small_demo, mount, capsys, monkeypatch):
    """The estimate passes (patched to 0) but the run fills the 3 MB disk: exit 6, one line, space freed,
    and an earlier output on that disk byte-identical."""
    disk = mount(size="3m")
    monkeypatch.setattr(workspace, "estimate_output_bytes", lambda source: 0)
    free = shutil.disk_usage(disk).free
    out = disk / "out"
    assert main(["run", str(photos), "-o", str(out), "--model", str(small_demo.model), *FAST]) == 6
    said = _said(capsys)
    assert len(said) == 1 and ("space" in said[0] or "full" in said[0]), said
    assert list(disk.iterdir()) == [] and shutil.disk_usage(disk).free == free


def test_a_mount_point_as_output_is_written_into(photos, small_demo, mount, monkeypatch):
    """A mount point (a Docker volume, say) cannot be renamed: the results are built inside it and moved up."""
    disk = mount()
    assert main(["run", str(photos), "-o", str(disk), "--model", str(small_demo.model), *FAST]) == 0
    assert _complete(disk) and not (disk / ".ffrecon-partial").exists()
    (disk / "keep.txt").write_text("the user's")
    assert main(["run", str(photos), "-o", str(disk), "--model", str(small_demo.model), "--overwrite", *FAST]) == 0
    assert _complete(disk) and (disk / "keep.txt").exists() and not (disk / ".ffrecon-old").exists()
    assert os.path.ismount(disk)


def test_a_bug_inside_a_stage_is_one_line_exit_1_and_leaves_out_as_it_was(
    photos, small_demo, tmp_path, monkeypatch, capsys
):
    """An unexpected error (a bug: street seed 245 once met numpy's LinAlgError in the refinement) ends in one line
    and its fix, exit 1, never a traceback unless -v asks; the earlier results stay."""
    out = tmp_path / "out"
    args = ["run", str(photos), "-o", str(out), "--model", str(small_demo.model), *FAST]
    assert main(args) == 0
    before = _tree(out)
    capsys.readouterr()

    def broken(*_args, **_kwargs):
        raise np.linalg.LinAlgError("Eigenvalues did not converge")

    monkeypatch.setattr("ffrecon.stages.run_feedforward_sharing", broken)
    assert main([*args, "--overwrite"]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and "internal error: LinAlgError: Eigenvalues did not converge" in err
    assert "run again with -v" in err.lower() and _tree(out) == before
    assert main([*args, "--overwrite", "-v"]) == 1
    err = capsys.readouterr().err
    assert "Traceback" in err and "broken" in err and _tree(out) == before
