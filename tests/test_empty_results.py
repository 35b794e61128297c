"""Empty results are verdicts, not crashes (issue 43, cases 4 and 10).

- All-zero masks (every pixel ignored) leave no fused point and no seed: the gate names the masks (check the
  polarity: 0 = ignore) and the run ends with exit 5 without exporting anything; with ``--force`` the files
  made of points are not written, the reason is in report.json and report.html, and the run ends with exit 0.
  Nothing is left beside OUT, and a later run without ``--masks`` has no ``masks/``.
- Six all-black photos: COLMAP and the refinement check no camera. That run fails (exit 5) unless forced;
  ``--no-colmap --no-refine`` checks nothing on purpose and passes.
"""

from __future__ import annotations

import json
import logging
import shutil
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from ffrecon import stages
from ffrecon.cli import main
from ffrecon.export.stage import ExportOptions, run_exports
from ffrecon.final_cameras import CameraSource, FinalCameras, require_checked
from ffrecon.geometry.rotations import quat_xyzw_to_matrix
from ffrecon.report.scene3d import scene_html
from ffrecon.sfm.crosscheck.gate_types import FailureCause, GateOptions, GatesResult, GateStatus, GateVerdict
from ffrecon.sfm.crosscheck.registration import diagnose_registration
from ffrecon.sfm.verify.verdicts import CameraEvidence, CameraStatus, EvidenceResult
from ffrecon.types import PinholeCamera
from ffrecon.workspace import staging_path

FAST = ["--no-colmap", "--no-refine", "--no-splat", "-q"]  # the model's cameras alone: seconds
TINY_VGGT = Path(__file__).resolve().parents[1] / "models" / "tiny_vggt.onnx"


def _err(capsys) -> str:
    return _said(capsys)[1]


def _said(capsys) -> tuple[str, str]:
    """``(stdout, stderr)``, checked for tracebacks and raw Python warnings."""
    out, err = capsys.readouterr()
    assert "Traceback" not in err and "RuntimeWarning" not in err, err
    return out, err


@pytest.fixture
def zero_masks(small_demo, tmp_path) -> Path:
    """A mask per demo photo, 0 (ignore) on every pixel: white drawn as black."""
    folder = tmp_path / "masks"
    folder.mkdir()
    for photo in sorted(small_demo.images.iterdir()):
        h, w = cv2.imread(str(photo)).shape[:2]
        cv2.imwrite(str(folder / f"{photo.stem}.png"), np.zeros((h, w), np.uint8))
    return folder


def test_all_zero_masks_fail_the_gate_naming_the_masks_and_export_nothing(small_demo, zero_masks, tmp_path, capsys):
    out = tmp_path / "out"
    run = ["run", str(small_demo.images), "-o", str(out), "--model", str(small_demo.model), "--masks", str(zero_masks)]
    assert main([*run, *FAST]) == 5
    err = _err(capsys)
    assert "the masks ignore every pixel of 8 of 8 frames" in err
    assert "ffrecon: GATE_FAILED - " in err  # with -q too, the run says why it stopped
    report = json.loads((out / "report.json").read_text())
    assert report["verdict"]["status"] == "gate_failed" and "mask polarity: 0 = ignore" in report["verdict"]["message"]
    gate = next(g for g in report["gates"] if g["name"] == "depth_coverage")
    assert gate["causes"] == ["masked"] and "try another model" not in gate["fix"]
    skipped = {s["stage"]: s["reason"] for s in report["skipped_stages"]}
    assert "gate 'depth_coverage' failed" in skipped["exports"]  # no exports after a failed gate
    assert not (out / "points.ply").exists() and not (out / "transforms.json").exists()
    assert not staging_path(out).exists()
    # A rerun without --masks into the folder: nothing of the earlier masks survives.
    assert (
        main(["run", str(small_demo.images), "-o", str(out), "--model", str(small_demo.model), "--resume", *FAST]) == 0
    )
    _err(capsys)
    assert not (out / "masks").exists() and (out / "points.ply").exists()
    frames = json.loads((out / "transforms.json").read_text())["frames"]
    assert not any("mask_path" in f for f in frames)
    record = json.loads((out / ".ffrecon" / "output.json").read_text())
    assert not any(f.startswith("masks/") for f in record["files"]) and not staging_path(out).exists()


def test_all_zero_masks_forced_skip_what_needs_points_with_the_reason(small_demo, zero_masks, tmp_path, capsys):
    out = tmp_path / "out"
    run = ["run", str(small_demo.images), "-o", str(out), "--model", str(small_demo.model), "--masks", str(zero_masks)]
    assert main([*run, "--no-colmap", "--no-refine", "--mesh", "--force"]) == 0
    _err(capsys)
    report = json.loads((out / "report.json").read_text())
    assert report["verdict"]["status"] == "ok"
    exports = report["exports"]
    assert exports["points_ply"] is None and exports["num_points"] == 0 and exports["mesh"] is None
    assert set(exports["not_written"]) == {"points.ply", "mesh.ply", "mesh.glb"}
    assert "mask polarity" in exports["not_written"]["points.ply"]
    skipped = {s["stage"]: s["reason"] for s in report["skipped_stages"]}
    assert skipped["splat"].startswith("no point to seed the splat")
    assert not any((out / f).exists() for f in ("points.ply", "mesh.ply", "mesh.glb", "splat.ply"))
    transforms = json.loads((out / "transforms.json").read_text())
    assert "ply_file_path" not in transforms and len(transforms["frames"]) == 8
    assert "Not written <b>points.ply</b>" in (out / "report.html").read_text()
    assert not staging_path(out).exists()


def test_a_run_resuming_an_interrupted_masked_one_keeps_no_masks(small_demo, zero_masks, tmp_path, capsys, monkeypatch):
    """Stopped after the capture wrote masks/, then run again without --masks: the earlier run's masks/ (in the
    staging folder it left) do not reach the new result."""
    out = tmp_path / "out"
    run = ["run", str(small_demo.images), "-o", str(out), "--model", str(small_demo.model), *FAST]

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(stages, "final_cameras", interrupt)
        assert main([*run, "--masks", str(zero_masks), "--force"]) == 130
    assert (staging_path(out) / "masks").is_dir()
    assert main(run) == 0
    _err(capsys)
    assert not (out / "masks").exists() and not staging_path(out).exists()
    assert not any("mask_path" in f for f in json.loads((out / "transforms.json").read_text())["frames"])


# --- nothing checked --------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def black(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("black")
    for k in range(6):
        cv2.imwrite(str(folder / f"b{k}.jpg"), np.zeros((96, 128, 3), np.uint8))
    return folder


@pytest.mark.parametrize(
    "flags, code",
    [
        ([], 5),  # COLMAP 0 of 6, refinement 0 usable frames
        (["--quick"], 5),  # the refinement's SIFT checks none either
        (["--no-refine"], 5),  # COLMAP, the only check, registered none
        (["--force"], 0),
        (["--no-colmap", "--no-refine"], 0),  # no check asked for: the model's cameras, said unchecked
    ],
)
def test_six_black_photos_fail_unless_nothing_was_asked_to_check(black, tmp_path, capsys, flags, code):
    out = tmp_path / "out"
    assert main(["run", str(black), "-o", str(out), "--model", str(TINY_VGGT), "--no-splat", *flags]) == code
    said, err = _said(capsys)
    report = json.loads((out / "report.json").read_text())
    gates = report["gates"] if isinstance(report["gates"], list) else []
    evidence = report["evidence"].get("gates", [])
    checked = [g for g in gates + evidence if g["name"] == "checked_share"]
    if flags == ["--no-colmap", "--no-refine"]:
        assert not checked and "not verified against an independent reconstruction" in report["cross_check_note"]
        return
    assert checked[0]["status"] == "fail" and "no camera could be checked" in checked[0]["reason"]
    assert "no camera could be checked" in err
    if code == 5:
        verdict = [line for line in said.splitlines() if line.startswith("ffrecon: GATE_FAILED")]
        assert len(verdict) == 1 and "checked_share: no camera could be checked" in verdict[0]
        assert "--force" in verdict[0] and not (out / "transforms.json").exists()
        assert "report: no 3D view" not in err


def _evidence(*statuses: CameraStatus, forced: bool = False) -> EvidenceResult:
    warn = GateVerdict("checked_share", GateStatus.WARN, 0.0, 1.0, "unchecked", blocking=False)
    per_image = tuple(CameraEvidence(f"f{k}.png", s, "") for k, s in enumerate(statuses))
    return EvidenceResult(GatesResult((warn,), forced), per_image, False)


class _Refine:
    registered = np.zeros(3, bool)


def test_require_checked_fails_only_when_no_kept_camera_was_checked():
    none = require_checked(_evidence(*[CameraStatus.UNCHECKED] * 3), "skipped", _Refine())
    assert none.gates.blocking and none.gates.failed[0].name == "checked_share"
    assert "the refinement confirmed none of the 3 frames" in none.gates.failed[0].reason
    assert not require_checked(
        _evidence(*[CameraStatus.UNCHECKED] * 3, forced=True), "skipped", _Refine()
    ).gates.blocking
    for checked in (CameraStatus.REFINED, CameraStatus.CORRECTED, CameraStatus.COLMAP_ONLY):
        one = _evidence(checked, CameraStatus.UNCHECKED, CameraStatus.UNCHECKED)
        assert require_checked(one, "skipped", _Refine()) is one


def test_masks_that_ignore_every_pixel_are_the_cause_before_blur_or_overlap():
    names = ["a.png", "b.png", "c.png"]
    options = GateOptions()
    assert diagnose_registration(None, names, 0, options, masked_out={"a.png", "b.png", "c.png"}) == (
        FailureCause.MASKED,
    )
    assert FailureCause.MASKED not in diagnose_registration(None, names, 0, options, masked_out=set())


def test_an_empty_cloud_writes_transforms_json_and_says_why_no_points(tmp_path):
    final = FinalCameras(
        (0, 1),
        ("a.png", "b.png"),
        np.tile(np.eye(4)[:3], (2, 1, 1)),
        (PinholeCamera(64, 48, 50.0, 50.0, 32.0, 24.0),) * 2,
        CameraSource.FEEDFORWARD,
    )
    empty = (np.zeros((0, 3)), np.zeros((0, 3)))
    result = run_exports(final, empty, "depth maps fused with the model's cameras", ExportOptions(mesh=True), tmp_path)
    assert result.points_ply is None and result.mesh_ply is None and not (tmp_path / "points.ply").exists()
    assert set(result.not_written) == {"points.ply", "mesh.ply", "mesh.glb"}
    assert "ply_file_path" not in json.loads(result.transforms_json.read_text())


def test_a_folder_with_no_cameras_has_no_3d_view_and_says_nothing(tmp_path, caplog):
    with caplog.at_level(logging.INFO, logger="ffrecon"):
        assert scene_html({}, tmp_path) == ""
    assert "no 3D view" not in caplog.text


def test_a_zero_quaternion_gives_nan_without_a_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rot = quat_xyzw_to_matrix(np.zeros((2, 4)))
    assert np.isnan(rot).all()


def test_frames_whose_masks_ignore_every_pixel_do_not_fail_the_model(small_demo, zero_masks, tmp_path, capsys):
    """Two of eight frames masked out whole: their depth is empty after the masks, which is not the model's fault
    (it used to end with exit 3, "depth is zero or negative everywhere ... re-export the model")."""
    masks = tmp_path / "some_masks"
    masks.mkdir()
    for k, path in enumerate(sorted(zero_masks.iterdir())):
        if k < 2:
            shutil.copy(path, masks / path.name)  # the rest have no mask: used whole
    out = tmp_path / "out"
    run = ["run", str(small_demo.images), "-o", str(out), "--model", str(small_demo.model), "--masks", str(masks)]
    code = main([*run, "--no-colmap", "--no-splat", "-q"])
    err = _err(capsys)
    assert code in (0, 5), err
    assert "re-export the model" not in err
