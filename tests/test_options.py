"""Options are checked where they are made (each options class's ``__post_init__``), so the command line and
the Python API refuse the same values with the same message, before any work."""

import dataclasses
import math

import numpy as np
import pycolmap
import pytest
from PIL import Image

from ffrecon.cli import main
from ffrecon.errors import InputError
from ffrecon.geometry.overlap import OverlapOptions
from ffrecon.models.distributed import RayOptions
from ffrecon.models.global_alignment import AlignmentOptions
from ffrecon.models.multiview import MultiviewOptions
from ffrecon.models.stage import FeedForwardOptions
from ffrecon.pipeline import RunOptions, check_run_options
from ffrecon.sfm.crosscheck.gate_types import GateOptions
from ffrecon.splat.clean import CleanOptions
from ffrecon.splat.densify import DensifyOptions
from ffrecon.splat.optimize import OptimizeOptions

NAN = float("nan")


# (flag named in the message, extra command-line arguments, the same options made through the Python API)
CLI_CASES = {
    "splat-seconds nan": (
        "--splat-seconds",
        ["--splat-seconds", "nan"],
        lambda t: OptimizeOptions.brief(max_seconds=NAN),
    ),
    "splat-seconds -5": (
        "--splat-seconds",
        ["--splat-seconds", "-5"],
        lambda t: OptimizeOptions.brief(max_seconds=-5.0),
    ),
    "splat-seconds 0": ("--splat-seconds", ["--splat-seconds", "0"], lambda t: OptimizeOptions.brief(max_seconds=0.0)),
    "min-registration nan": (
        "--min-registration",
        ["--min-registration", "nan"],
        lambda t: GateOptions(min_registration_ratio=NAN),
    ),
    "min-registration -0.1": (
        "--min-registration",
        ["--min-registration", "-0.1"],
        lambda t: GateOptions(min_registration_ratio=-0.1),
    ),
    "min-registration 1.5": (
        "--min-registration",
        ["--min-registration", "1.5"],
        lambda t: GateOptions(min_registration_ratio=1.5),
    ),
    "threads -4": ("--threads", ["--threads", "-4"], lambda t: FeedForwardOptions(threads=-4)),
    "threads 0": ("--threads", ["--threads", "0"], lambda t: FeedForwardOptions(threads=0)),
    "ray-workers 0": ("--ray-workers", ["--ray", "--ray-workers", "0"], lambda t: RayOptions(workers=0)),
    "ray-gpus -1": ("--ray-gpus", ["--ray", "--ray-gpus", "-1"], lambda t: RayOptions(gpus_per_worker=-1.0)),
    "chunk-size 0": ("--chunk-size", ["--chunk-size", "0"], lambda t: MultiviewOptions(chunk_size=0)),
    "chunk-size -1": ("--chunk-size", ["--chunk-size", "-1"], lambda t: MultiviewOptions(chunk_size=-1)),
    "chunk-overlap 0": ("--chunk-overlap", ["--chunk-overlap", "0"], lambda t: MultiviewOptions(chunk_overlap=0)),
    "chunk-overlap = chunk-size": (
        "--chunk-overlap",
        ["--chunk-size", "4", "--chunk-overlap", "4"],
        lambda t: MultiviewOptions(chunk_size=4, chunk_overlap=4),
    ),
    "chunk-overlap > chunk-size": (
        "--chunk-overlap",
        ["--chunk-size", "3", "--chunk-overlap", "5"],
        lambda t: MultiviewOptions(chunk_size=3, chunk_overlap=5),
    ),
    "reference missing": (
        "--reference",
        ["--reference", "{tmp}/missing"],
        lambda t: check_run_options(None, RunOptions(reference=t / "missing")),
    ),
    "reference plain folder": (
        "--reference",
        ["--reference", "{tmp}/plain"],
        lambda t: check_run_options(None, RunOptions(reference=t / "plain")),
    ),
}


@pytest.fixture
def photos(tmp_path):
    """Three small generated photos (a run would read them; a refused one never does), and a plain folder."""
    (tmp_path / "plain").mkdir()
    folder = tmp_path / "photos"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for k in range(3):
        Image.fromarray(rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)).save(folder / f"photo{k}.png")
    return folder


@pytest.mark.parametrize("case", list(CLI_CASES))
def test_cli_refuses_bad_values_before_any_work(case, photos, tmp_path, capsys):
    flag, extra, _ = CLI_CASES[case]
    before = sorted(p.name for p in tmp_path.iterdir())
    out = tmp_path / "out"
    args = [a.format(tmp=tmp_path) for a in extra]
    assert main(["run", str(photos), "-o", str(out), *args]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 2 and "Traceback" not in captured.err, captured.err
    assert lines[0].startswith("ffrecon: error: ") and flag in lines[0], lines[0]
    assert lines[1].startswith("  fix: ") and flag in lines[1], lines[1]
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no staging folder beside OUT either


@pytest.mark.parametrize("case", list(CLI_CASES))
def test_python_api_gives_the_cli_message(case, photos, tmp_path, capsys):
    _, extra, make = CLI_CASES[case]
    with pytest.raises(InputError) as err:
        make(tmp_path)
    assert main(["run", str(photos), "-o", str(tmp_path / "out"), *[a.format(tmp=tmp_path) for a in extra]]) == 2
    assert capsys.readouterr().err.splitlines()[:2] == [
        f"ffrecon: error: {err.value.problem}",
        f"  fix: {err.value.fix}",
    ]


def test_brief_preset_checks_its_overrides():
    with pytest.raises(InputError, match="--splat-seconds.*got nan") as err:
        OptimizeOptions.brief(max_seconds=float("nan"))
    assert err.value.exit_code == 2 and "--splat-seconds" in err.value.fix
    with pytest.raises(InputError, match="OptimizeOptions.iterations"):
        OptimizeOptions.brief(iterations=0)
    with pytest.raises(InputError, match="resolution_schedule factor"):
        OptimizeOptions.brief(resolution_schedule=((0.0, 0),))


def _options_under(options, seen=None) -> list:
    """Every options object reachable from ``options`` (capture's are checked in ffrecon.capture)."""
    seen = {} if seen is None else seen
    for f in dataclasses.fields(options):
        value = getattr(options, f.name)
        if dataclasses.is_dataclass(value) and type(value).__name__ != "CaptureOptions":
            seen.setdefault(type(value).__name__, value)
            _options_under(value, seen)
    return list(seen.values())


FLOAT_FIELDS = [
    (options, f.name)
    for options in _options_under(RunOptions())
    for f in dataclasses.fields(options)
    if isinstance(getattr(options, f.name), float)
]


@pytest.mark.parametrize("options, name", FLOAT_FIELDS, ids=[f"{type(o).__name__}.{n}" for o, n in FLOAT_FIELDS])
@pytest.mark.parametrize("value", [NAN, math.inf, -1.0])
def test_no_number_of_a_run_takes_nan_infinity_or_a_negative(options, name, value):
    with pytest.raises(InputError, match=f"{type(options).__name__}.{name}"):
        dataclasses.replace(options, **{name: value})


def test_legal_edge_values_stay_legal():
    RunOptions()
    RunOptions.quick()
    OptimizeOptions(lr_means=0.0, lr_scales=0.0, ssim_weight=0.0, plateau_window=0, densify=None)
    OptimizeOptions.brief(max_seconds=1e9, iterations=1, sh_degree=0, threads=1)
    GateOptions(min_registration_ratio=0.0, min_points=0)
    GateOptions(min_registration_ratio=1)
    MultiviewOptions(chunk_size=2, chunk_overlap=1)
    MultiviewOptions(chunk_overlap=10)  # without a chunk size, capped at the size chosen less one
    FeedForwardOptions(threads=None)
    FeedForwardOptions(threads=np.int64(2))
    AlignmentOptions(iterations=0)
    DensifyOptions(grad_threshold=0.0)
    CleanOptions(floater_std_ratio=0, crop_box=((-1, -1, -1), (1, 1, 1)))
    OverlapOptions(min_pairs_per_image=0)


def test_clean_crop_box_must_be_a_box():
    with pytest.raises(InputError, match="crop_box"):
        CleanOptions(crop_box=((0, 0, 0), (1, -1, 1)))


def _model(folder, num_images: int):
    """A COLMAP model with ``num_images`` registered images (and no points)."""
    rec = pycolmap.Reconstruction()
    camera = pycolmap.Camera(model="SIMPLE_PINHOLE", width=32, height=24, params=[30.0, 16.0, 12.0], camera_id=1)
    rec.add_camera_with_trivial_rig(camera)
    for k in range(num_images):
        image = pycolmap.Image(name=f"photo{k}.png", camera_id=1, image_id=k + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d())
    folder.mkdir(parents=True)
    rec.write_binary(str(folder))
    return folder


def test_reference_is_a_readable_model_with_registered_images(tmp_path):
    check_run_options(None, RunOptions(reference=_model(tmp_path / "good", 2)))
    _model(tmp_path / "project" / "sparse" / "0", 2)
    with pytest.raises(InputError, match="--reference .*project is not a COLMAP model folder") as err:
        check_run_options(None, RunOptions(reference=tmp_path / "project"))
    assert err.value.fix == f"pass --reference {tmp_path / 'project' / 'sparse' / '0'}"
    with pytest.raises(InputError, match="no registered images"):
        check_run_options(None, RunOptions(reference=_model(tmp_path / "empty", 0)))


def test_ground_truth_is_a_synthetic_scene_folder(tmp_path):
    with pytest.raises(InputError, match="ground_truth.json"):
        check_run_options(None, RunOptions(ground_truth=tmp_path))
