"""Resume keys from content: a photo replaced by another of the same byte size and modification time (what
``cp -p``, ``rsync -a`` and ``tar`` make; BMPs of one size always match) is a change, and unchanged files are
not read again (the hashes are cached by stat in ``OUT/.ffrecon/file_hashes.json``)."""

import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np

import ffrecon.resume as resume
from ffrecon.cli import main
from ffrecon.resume import FileHashes, content_hash, file_key

FAST = ["--no-colmap", "--no-refine", "--no-splat", "-q"]


def _bmp_photos(small_demo, folder: Path, count: int = 6) -> Path:
    """``count`` demo photos as BMPs: every file has the same byte size."""
    folder.mkdir()
    for png in sorted(small_demo.images.glob("*.png"))[:count]:
        cv2.imwrite(str(folder / f"{png.stem}.bmp"), cv2.imread(str(png)))
    return folder


def _reused(out: Path) -> dict[str, bool]:
    """Each stage's "reused" (the run's own "startup" and "report" entries of the timings are no stages)."""
    timings = json.loads((out / "report.json").read_text())["timings"]
    return {stage: t["reused"] for stage, t in timings.items() if stage not in ("startup", "report")}


def test_a_photo_replaced_with_the_same_size_and_mtime_runs_again(small_demo, tmp_path, monkeypatch):
    photos, out = _bmp_photos(small_demo, tmp_path / "photos"), tmp_path / "out"
    command = ["run", str(photos), "-o", str(out), "--model", str(small_demo.model), *FAST]
    assert main(command) == 0
    assert (out / ".ffrecon" / "file_hashes.json").is_file()

    hashed = []
    monkeypatch.setattr(resume, "content_hash", lambda p: hashed.append(p) or content_hash(p))
    assert main([*command, "--resume"]) == 0
    assert all(_reused(out).values()), _reused(out)
    assert hashed == []  # nothing changed: every hash came from the cache

    target = photos / "frame_000.bmp"
    before = target.stat()
    new_pixels = cv2.imread(str(photos / "frame_003.bmp"))[::-1].copy()  # other pixels, same size
    cv2.imwrite(str(target), new_pixels)
    os.utime(target, ns=(before.st_atime_ns, before.st_mtime_ns))
    assert (target.stat().st_size, target.stat().st_mtime_ns) == (before.st_size, before.st_mtime_ns)

    assert main([*command, "--resume"]) == 0
    assert not any(_reused(out).values()), _reused(out)  # the capture changed, and everything reads it
    assert [p.name for p in hashed] == ["frame_000.bmp"]  # only the changed photo was read again
    np.testing.assert_array_equal(cv2.imread(str(out / "images" / "frame_000.bmp")), new_pixels)


def test_keys_are_stable_and_follow_the_content(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    for k in range(3):
        (folder / f"{k}.bmp").write_bytes(bytes([k]) * 1000)
    cache = tmp_path / "file_hashes.json"
    first = file_key(folder, FileHashes(cache))
    assert file_key(folder, FileHashes(cache)) == first == file_key(folder)  # from the cache, and without it
    copy = tmp_path / "copy"
    shutil.copytree(folder, copy)  # other inodes and times, same names and bytes: the same files' hashes
    assert FileHashes(None).digest(copy / "1.bmp") == FileHashes(cache).digest(folder / "1.bmp")
    stat = (folder / "1.bmp").stat()
    (folder / "1.bmp").write_bytes(b"\x07" * 1000)
    os.utime(folder / "1.bmp", ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert file_key(folder, FileHashes(cache)) != first


def test_a_sparse_file_hashes_without_reading_its_holes(tmp_path):
    """The key of a huge sparse file (an option file gone wrong) is made at once; its reader then refuses it."""
    sparse, dense = tmp_path / "sparse.bin", tmp_path / "dense.bin"
    with open(sparse, "wb") as file:
        file.truncate(20 << 30)
    assert content_hash(sparse) is not None  # seconds would mean the holes were read (test time shows it)
    small = tmp_path / "small.bin"
    small.write_bytes(b"\0" * 10)
    dense.write_bytes(b"\0" * 11)
    assert content_hash(small) != content_hash(dense)  # the size is part of the hash
    assert content_hash(tmp_path) is None and content_hash(Path("/dev/zero")) is None


def test_every_file_a_stage_is_given_is_in_its_key(tmp_path):
    """The user files the options name are keyed by content through the stage that reads them: a vocabulary tree
    replaced at the same path re-runs COLMAP's matching (it was keyed by its path alone)."""
    import dataclasses

    from ffrecon.options import RunOptions
    from ffrecon.stages import COLMAP_MATCHING

    tree = tmp_path / "vocab_tree.bin"
    tree.write_bytes(b"one tree")
    options = dataclasses.replace(RunOptions(), colmap=dataclasses.replace(RunOptions().colmap, vocab_tree_path=tree))
    assert tree in COLMAP_MATCHING.files(None, options)
    first = file_key(tree)
    tree.write_bytes(b"another!")
    assert file_key(tree) != first
