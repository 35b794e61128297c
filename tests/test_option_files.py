"""Every option that names a file or folder, fed what a user can point it at by mistake: a character device,
a FIFO, a folder, an empty file, a huge sparse file, random bytes. Each ends with exit 2, one line and its fix,
no traceback, no hang, no memory blow-up, and nothing left beside OUT (issue 43, case 6). Also: --poses that
are not rotations or all at one place (case 8), and corrupt --vocab-tree files (case 5)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ffrecon.cli import main
from ffrecon.errors import InputError
from ffrecon.formats.nerfstudio import write_transforms
from ffrecon.formats.poses import read_poses
from ffrecon.sfm.crosscheck.retrieval import check_vocab_tree
from ffrecon.types import PinholeCamera

FAST = ["--no-colmap", "--no-refine", "--no-splat", "-q"]
OPTIONS = ("--intrinsics", "--poses", "--masks", "--reference")
KINDS = ("device", "directory", "empty", "sparse", "random")


def _make(kind: str, folder: Path, option: str) -> Path:
    """A path of ``kind``; --poses files end in .json (so the transforms.json reader is the one tried)."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / (f"{kind}.json" if option == "--poses" else kind)
    if kind == "device":
        return Path("/dev/zero")
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "directory":
        path.mkdir()
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "sparse":
        with open(path, "wb") as file:
            file.truncate(20 << 30)  # 20 GB, nothing written
    elif kind == "random":
        path.write_bytes(np.random.default_rng(0).bytes(4096))
    return path


def _hidden(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def _check_refused(code: int, err: str, out: Path, hidden_before: list[str]) -> None:
    assert "Traceback" not in err, err
    said = [line for line in err.splitlines() if line.startswith("ffrecon:")]
    assert code == 2 and len(said) == 1, (code, err)
    assert "fix:" in err, err
    assert not out.exists() and _hidden(out.parent) == hidden_before, _hidden(out.parent)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("option", OPTIONS)
def test_an_option_file_of_the_wrong_kind_is_one_line_and_exit_2(small_demo, tmp_path, capsys, option, kind):
    path = _make(kind, tmp_path / "given", option)
    out = tmp_path / "runs" / "out"
    out.parent.mkdir()
    hidden = _hidden(out.parent)
    code = main(
        ["run", str(small_demo.images), "-o", str(out), "--model", str(small_demo.model), *FAST, option, str(path)]
    )
    err = capsys.readouterr().err
    _check_refused(code, err, out, hidden)
    assert option in err or kind == "directory", err  # the line names the option (a folder: what it lacks)


_FIFO_SCRIPT = """
import json, sys
from ffrecon.cli import main
for option, path, out in json.loads(sys.argv[1]):
    code = main(["run", sys.argv[2], "-o", out, "--model", sys.argv[3], "--no-colmap", "--no-refine", "--no-splat",
                 "-q", option, path])
    print(json.dumps([option, code]), flush=True)
"""


def test_a_fifo_never_hangs(small_demo, tmp_path):
    """One child process runs every option with a FIFO (a hang fails on the timeout, naming the option it hung in)."""
    cases = []
    for option in OPTIONS:
        fifo = _make("fifo", tmp_path / "given" / option.strip("-"), option)
        cases.append((option, str(fifo), str(tmp_path / "runs" / option.strip("-") / "out")))
        Path(cases[-1][2]).parent.mkdir(parents=True)
    command = [sys.executable, "-c", _FIFO_SCRIPT, json.dumps(cases), str(small_demo.images), str(small_demo.model)]
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=120)
    except subprocess.TimeoutExpired as err:
        pytest.fail(f"hung after {err.stdout!r}")
    assert "Traceback" not in done.stderr, done.stderr
    codes = dict(json.loads(line) for line in done.stdout.splitlines())
    assert codes == dict.fromkeys(OPTIONS, 2), done.stderr
    said = [line for line in done.stderr.splitlines() if line.startswith("ffrecon:")]
    assert len(said) == len(OPTIONS) and all("FIFO" in line or "not a COLMAP model" in line for line in said), said
    for _, _, out in cases:
        assert not Path(out).exists() and _hidden(Path(out).parent) == []


def test_model_files_inside_a_folder_option_are_checked(tmp_path):
    """--poses and --reference folders: a FIFO or device in place of images.bin is refused before COLMAP opens it."""
    from ffrecon.sfm.compare.comparisons import check_references

    folder = tmp_path / "model"
    folder.mkdir()
    (folder / "images.bin").write_bytes(bytes(64))
    os.mkfifo(folder / "cameras.bin")
    (folder / "points3D.bin").symlink_to("/dev/zero")
    for call, option in ((read_poses, "--poses"), (lambda p: check_references(None, p), "--reference")):
        with pytest.raises(InputError, match=f"{option} .*cameras.bin is a FIFO"):
            call(folder)
        (folder / "cameras.bin").unlink()
        with pytest.raises(InputError, match=f"{option} .*points3D.bin is a character device, not a regular file"):
            call(folder)
        os.mkfifo(folder / "cameras.bin")


# --- case 8: poses that are not rigid, or all at one place -------------------------------------------------------


def _transforms(tmp_path: Path, cam_from_world: np.ndarray) -> Path:
    path = tmp_path / "transforms.json"
    names = [f"images/frame_{k:03d}.png" for k in range(len(cam_from_world))]
    write_transforms(path, names, cam_from_world, [PinholeCamera(224, 168, 200.0, 200.0, 112.0, 84.0)] * len(names))
    return path


def _ring(n: int = 6) -> np.ndarray:
    """``[n, 3, 4]`` cam_from_world of cameras on a circle, looking at the origin."""
    poses = []
    for angle in np.linspace(0, 2 * np.pi, n, endpoint=False):
        centre = np.array([np.cos(angle), 0.0, np.sin(angle)]) * 3
        z = -centre / np.linalg.norm(centre)
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        rotation = np.stack([x, np.cross(z, x), z])
        poses.append(np.hstack([rotation, (-rotation @ centre)[:, None]]))
    return np.stack(poses)


def test_good_poses_pass_and_nearly_orthonormal_ones_are_projected(tmp_path):
    poses = _ring()
    noisy = poses.copy()
    noisy[:, :3, :3] += np.random.default_rng(0).normal(0, 1e-5, (len(poses), 3, 3))
    known = read_poses(_transforms(tmp_path, noisy))
    for _, pose in known.by_name:
        np.testing.assert_allclose(pose[:, :3].T @ pose[:, :3], np.eye(3), atol=1e-12)
        assert np.linalg.det(pose[:, :3]) == pytest.approx(1.0)


@pytest.mark.parametrize(
    ("change", "said"),
    [
        (lambda p: p[:, :3, 3].__setitem__(slice(None), 0) or _at_origin(p), "are at one place"),
        (lambda p: p[2, :3, :3].__imul__(3 ** (1 / 3)), "frame_002.png"),  # determinant 3
        (lambda p: p[4, :3, :3].__imul__(-1), "frame_004.png"),  # a reflection (det -1)
    ],
    ids=["one place", "det 3", "reflection"],
)
def test_poses_that_are_not_rigid_or_all_at_one_place_are_refused(tmp_path, change, said):
    poses = _ring()
    change(poses)
    with pytest.raises(InputError, match=said) as caught:
        read_poses(_transforms(tmp_path, poses))
    assert "\n" not in caught.value.problem


def _at_origin(poses: np.ndarray) -> None:
    poses[:, :, 3] = 0.0  # every camera centre at the origin (rotations differ: a camera turning on one spot)


# --- case 5: a corrupt --vocab-tree -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_tree(tmp_path_factory) -> Path:
    """A valid faiss-format vocabulary tree of 16 words, built by pycolmap (a second)."""
    import pycolmap

    path = tmp_path_factory.mktemp("vocab") / "tree.bin"
    index = pycolmap.VisualIndex.create(128, 64)
    options = pycolmap.VisualIndex.BuildOptions(num_visual_words=16, num_iterations=5, num_rounds=1, num_threads=1)
    data = np.random.default_rng(0).random((2000, 128)).astype(np.float32) * 255
    index.build(options, pycolmap.FeatureDescriptorsFloat(pycolmap.FeatureExtractorType.SIFT, data))
    index.write(str(path))
    return path


def test_a_corrupt_vocab_tree_is_refused_before_colmap_reads_it(tiny_tree, tmp_path):
    cache = tmp_path / "cache"
    assert check_vocab_tree(tiny_tree, cache_dir=cache) == tiny_tree
    assert (cache / "vocab_trees_read.json").is_file()  # read once per file: the next check does not start pycolmap
    truncated = tmp_path / "truncated.bin"
    truncated.write_bytes(tiny_tree.read_bytes()[: tiny_tree.stat().st_size // 2])  # a good header, then cut
    flann = tmp_path / "flann.bin"
    flann.write_bytes((32768).to_bytes(8, "little") + (128).to_bytes(8, "little") + bytes(4096))
    cases = {
        truncated: "not a vocabulary tree COLMAP can read",
        flann: "a FLANN-format tree",
        _make("random", tmp_path / "given", ""): "not a vocabulary tree",
        Path("/dev/zero"): "character device",
        _make("empty", tmp_path / "given", ""): "is empty",
        _make("sparse", tmp_path / "given", ""): "more than such a file can be",
    }
    for path, said in cases.items():
        with pytest.raises(InputError, match=said):
            check_vocab_tree(path, cache_dir=cache)


def test_a_corrupt_vocab_tree_stops_the_run_with_exit_2(small_demo, tiny_tree, tmp_path):
    """Before: COLMAP's matching thread aborted the process (SIGABRT, exit 134) and left .OUT.partial; in a child
    process, so that a regression fails this test and not the whole session."""
    truncated = tmp_path / "truncated.bin"
    truncated.write_bytes(tiny_tree.read_bytes()[:30000])  # what aborted the run before
    out = tmp_path / "runs" / "out"
    out.parent.mkdir()
    command = ["run", str(small_demo.images), "-o", str(out), "--model", str(small_demo.model), "--no-refine"]
    command += ["--no-splat", "-q", "--pairing", "vocab_tree", "--vocab-tree", str(truncated)]
    env = {**os.environ, "FFRECON_CACHE": str(tmp_path / "cache")}
    done = subprocess.run(
        [sys.executable, "-m", "ffrecon", *command], capture_output=True, text=True, timeout=300, env=env
    )
    _check_refused(done.returncode, done.stderr, out, [])
    assert "--vocab-tree" in done.stderr and "not a vocabulary tree COLMAP can read" in done.stderr
