"""Inputs that capture must refuse, skip or normalise before any work (issue 43, cases 2, 7, 9, 11, 14).

Every refusal is one line with the fix (exit 2), never a traceback; cheap: photos of 64x48 px, and CLI
runs that stop at capture.
"""

import logging
import re

import cv2
import numpy as np
import pytest
from PIL import Image

from ffrecon.capture import CaptureOptions, run_capture
from ffrecon.capture.images import MAX_FRAME_ASPECT, MIN_FRAME_SIDE, load_photo
from ffrecon.capture.names import name_clashes
from ffrecon.cli import main
from ffrecon.errors import InputError
from tests.conftest import MODELS

FAST = ["--model", str(MODELS / "tiny_vggt.onnx"), "--no-colmap", "--no-refine", "--no-splat", "-q"]


def _pattern(h=48, w=64, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return cv2.resize(rng.integers(0, 255, (h // 4, w // 4, 3), dtype=np.uint8), (w, h), interpolation=cv2.INTER_CUBIC)


def _photos(folder, names) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for k, name in enumerate(names):
        Image.fromarray(_pattern(seed=k)).save(folder / name, quality=95)


def _run(args, capsys) -> tuple[int, list[str]]:
    code = main(["run", *map(str, args), *FAST])
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    return code, [line for line in err.splitlines() if line.startswith("ffrecon:")]


# --- case 2: names that would share outputs ----------------------------------------------------------


def test_name_clashes_ignore_extension_and_case():
    assert name_clashes(["a.jpg", "a.png", "b.JPG", "b.jpg", "c.jpg", "C2.jpg"]) == [
        ["a.jpg", "a.png"],
        ["b.JPG", "b.jpg"],
    ]
    assert name_clashes(["a.jpg", "A.JPG"]) == [["a.jpg", "A.JPG"]]  # one file on macOS and Windows
    assert name_clashes(["a.jpg", "a.jpg.png"]) == [["a.jpg", "a.jpg.png"]]  # a.jpg.png: the mask name of both
    assert name_clashes(["a.jpg", "ab.jpg", "a_1.png"]) == []


@pytest.mark.parametrize("skip", [False, True])
def test_photos_sharing_a_stem_are_refused_before_any_work(tmp_path, capsys, monkeypatch, skip):
    src = tmp_path / "in"
    _photos(src, ["a.jpg", "a.png", "b.JPG", "b.jpg", "c.jpg", "d.jpg"])
    decoded = []
    monkeypatch.setattr("ffrecon.capture.load_photo", lambda path, **kw: decoded.append(path))
    code, said = _run([src, "-o", tmp_path / "out", *(["--skip-bad-images"] if skip else [])], capsys)
    assert code == 2 and len(said) == 1 and decoded == []
    assert "a.jpg and a.png; b.JPG and b.jpg" in said[0] and "overwrite each other" in said[0]
    assert not (tmp_path / "out" / "feedforward").exists()


def test_video_frame_names_never_clash_or_hold_spaces(tmp_path):
    path = tmp_path / "my clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48))
    for k in range(4):
        writer.write(_pattern(seed=k))
    writer.release()
    cap = run_capture(path, CaptureOptions(video_frames=2), tmp_path / "out")
    assert len(cap.names) == 2 and all(re.fullmatch(r"my_clip_00000\d\.png", n) for n in cap.names), cap.names
    assert all((tmp_path / "out" / "images" / n).is_file() for n in cap.names)


# --- case 7: photos too small for a stage ------------------------------------------------------------


def test_tiny_photos_are_refused_up_front_or_skipped(tmp_path, capsys):
    src = tmp_path / "in"
    _photos(src, [f"{k}.png" for k in range(6)])
    Image.fromarray(_pattern()[:8, :8]).save(src / "tiny.png")
    Image.fromarray(cv2.resize(_pattern(), (640, 12))).save(src / "strip.png")  # DIS flow crashed on 640x12
    code, said = _run([src, "-o", tmp_path / "out"], capsys)
    assert code == 2 and len(said) == 1
    assert "tiny.png is 8x8 px" in said[0] and "strip.png is 640x12 px" in said[0]
    assert f"at least {MIN_FRAME_SIDE} px on the short side" in said[0]
    cap = run_capture(src, CaptureOptions(skip_bad_images=True), tmp_path / "o2")
    assert len(cap.names) == 6 and dict(cap.skipped)["tiny.png"].startswith("tiny.png is 8x8 px; every stage needs")
    Image.fromarray(cv2.resize(_pattern(), (MAX_FRAME_ASPECT * 20 + 20, 20))).save(src / "panorama.png")
    with pytest.raises(InputError, match=f"panorama.png is 660x20 px, 33 times .* at most {MAX_FRAME_ASPECT} times"):
        load_photo(src / "panorama.png")


def test_the_smallest_frames_accepted_run_in_every_stage_that_limits_them():
    """The limits are what the stages take: DIS flow (dense evidence) and the models' preprocessing."""
    from ffrecon.models.pairwise import preprocess_pairwise
    from ffrecon.models.vggt import preprocess_vggt

    rng = np.random.default_rng(0)
    for w, h in [(MIN_FRAME_SIDE, MIN_FRAME_SIDE), (MIN_FRAME_SIDE * MAX_FRAME_ASPECT, MIN_FRAME_SIDE), (16, 640)]:
        a, b = (rng.integers(0, 255, (h, w), dtype=np.uint8) for _ in range(2))
        assert cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(a, b, None).shape == (h, w, 2)
    for w, h in [(MIN_FRAME_SIDE, MIN_FRAME_SIDE), (1600, 1600 // MAX_FRAME_ASPECT), (1600 // MAX_FRAME_ASPECT, 1600)]:
        image = np.zeros((h, w, 3), np.uint8)
        assert min(preprocess_pairwise([image])[0].shape[-2:]) >= 16
        assert min(preprocess_vggt([image])[0].shape[-2:]) >= 14


# --- case 9: absurd EXIF focal lengths ---------------------------------------------------------------


def _exif_focal(path, *, focal_px=None, focal_35mm=None) -> None:
    img = Image.fromarray(_pattern())
    exif = img.getexif()
    sub = exif.get_ifd(0x8769)
    if focal_px is not None:  # FocalLength 4 mm, focal-plane resolution in pixels per mm (unit 4)
        sub[0x920A], sub[0xA20E], sub[0xA210] = 4.0, focal_px / 4.0, 4
    if focal_35mm is not None:
        sub[0xA405] = focal_35mm
    img.save(path, exif=exif, quality=95)


def test_absurd_exif_focal_lengths_are_ignored_with_one_warning(tmp_path, caplog):
    _exif_focal(tmp_path / "huge.jpg", focal_px=1.17e6)
    _exif_focal(tmp_path / "absurd.jpg", focal_px=1.7e14, focal_35mm=26)  # the 35 mm equivalent is fine
    _exif_focal(tmp_path / "fine.jpg", focal_px=60.0)
    with caplog.at_level(logging.WARNING, logger="ffrecon.capture"):
        assert load_photo(tmp_path / "huge.jpg").focal_prior_px is None
        assert load_photo(tmp_path / "absurd.jpg").focal_prior_px == pytest.approx(26 / 36 * 64)
        assert load_photo(tmp_path / "fine.jpg").focal_prior_px == pytest.approx(60.0)
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2 and "\n" not in "".join(lines)
    assert lines[0].startswith("huge.jpg: EXIF focal length 1.17e+06 px") and "ignored" in lines[0]
    assert lines[1].startswith("absurd.jpg: EXIF focal length 1.7e+14 px")


# --- case 11: frames in OUT/images are upright 8-bit RGB ---------------------------------------------


def _odd_formats(src) -> dict[str, np.ndarray]:
    """Photos that are not upright 8-bit RGB, and the upright RGB each should become."""
    src.mkdir()
    rgb = _pattern()
    img = Image.fromarray(rgb)
    img.convert("CMYK").save(src / "cmyk.jpg", quality=95)
    img.convert("P").save(src / "palette.png")
    img.convert("L").save(src / "grey.png")
    img.convert("LA").save(src / "grey_alpha.png")
    img.convert("RGBA").save(src / "rgba.png")
    cv2.imwrite(str(src / "deep.png"), rgb[..., ::-1].astype(np.uint16) * 257)
    exif = img.getexif()
    exif[0x0112] = 6
    img.save(src / "rotated.jpg", exif=exif, quality=95)
    img.save(src / "plain.jpg", quality=95)
    expected = {p.name: np.asarray(Image.open(p).convert("RGB")) for p in src.iterdir() if p.name != "deep.png"}
    expected["deep.png"] = rgb
    expected["rotated.jpg"] = np.rot90(expected["rotated.jpg"], k=-1)
    return expected


def test_frames_not_upright_8bit_rgb_are_reencoded(tmp_path):
    expected = _odd_formats(tmp_path / "in")
    cap = run_capture(tmp_path / "in", CaptureOptions(), tmp_path / "out")
    assert sorted(cap.names) == sorted(expected)
    for frame in cap.frames:
        with Image.open(frame.path) as img:
            assert (img.mode, img.getexif().get(0x0112, 1)) == ("RGB", 1), frame.name
            pixels = np.asarray(img)
        diff = np.abs(pixels.astype(int) - expected[frame.name].astype(int))
        assert diff.mean() < 3.0, frame.name  # JPEG re-encoding of this busy pattern: 2.2 for cmyk.jpg
    assert (tmp_path / "out/images/plain.jpg").read_bytes() == (tmp_path / "in/plain.jpg").read_bytes()
    assert (tmp_path / "out/images/cmyk.jpg").read_bytes() != (tmp_path / "in/cmyk.jpg").read_bytes()


# --- case 14: white space in names -------------------------------------------------------------------


def test_names_with_white_space_are_refused_up_front_in_every_mode(tmp_path, capsys):
    src = tmp_path / "in"
    _photos(src, ["a.jpg", "b c.jpg", "d\te.jpg", "f.jpg", "g.jpg", "h.jpg"])
    code, said = _run([src, "-o", tmp_path / "out"], capsys)  # --no-colmap --no-refine: accepted before
    assert code == 2 and len(said) == 1
    assert "2 photo name(s)" in said[0] and "'b c.jpg'" in said[0] and "white space" in said[0]
