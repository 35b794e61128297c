"""Capture: formats, bit depths, EXIF orientation and focal length, video frames, quality flags, bad input."""

import pickle

import cv2
import numpy as np
import pytest
from PIL import Image, ImageOps, PngImagePlugin

from ffrecon.capture import CaptureOptions, run_capture
from ffrecon.capture.images import load_image, read_exif
from ffrecon.capture.quality import assess_capture, measure_frame
from ffrecon.capture.video import extract_video_frames
from ffrecon.errors import InputError


def _pattern(h=60, w=80, seed=0):
    rng = np.random.default_rng(seed)
    img = cv2.resize(rng.integers(0, 255, (h // 4, w // 4, 3), dtype=np.uint8), (w, h), interpolation=cv2.INTER_CUBIC)
    return img


@pytest.mark.parametrize("ext", [".jpg", ".png", ".tif", ".webp", ".bmp"])
def test_formats_load_as_rgb8(tmp_path, ext):
    rgb = _pattern()
    path = tmp_path / f"a{ext}"
    Image.fromarray(rgb).save(
        path, **({"quality": 100} if ext == ".jpg" else {"lossless": True} if ext == ".webp" else {})
    )
    out, focal, converted = load_image(path)
    assert out.shape == rgb.shape and out.dtype == np.uint8 and focal is None and not converted
    if ext == ".jpg":  # lossy: compare with Pillow's decode of the same file (decoders differ by rounding)
        with Image.open(path) as ref:
            diff = np.abs(out.astype(int) - np.asarray(ref.convert("RGB")).astype(int))
        assert diff.mean() < 1.0 and diff.max() <= 8
    else:
        assert np.array_equal(out, rgb)


def test_grayscale_rgba_and_16bit(tmp_path):
    rgb = _pattern()
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    cv2.imwrite(str(tmp_path / "g.png"), gray)
    out, _, converted = load_image(tmp_path / "g.png")
    assert (
        converted and out.shape == rgb.shape and np.array_equal(out[..., 0], gray) and np.array_equal(out[..., 1], gray)
    )
    # RGBA: fully transparent pixels become white, opaque ones keep their colour.
    rgba = np.dstack([rgb, np.full(rgb.shape[:2], 255, np.uint8)])
    rgba[:10, :, 3] = 0
    Image.fromarray(rgba).save(tmp_path / "a.png")
    out, _, converted = load_image(tmp_path / "a.png")
    assert converted and np.all(out[:10] == 255) and np.array_equal(out[10:], rgb[10:])
    # 16-bit RGB TIFF: scaled to 8 bits.
    rgb16 = rgb.astype(np.uint16) * 257
    cv2.imwrite(str(tmp_path / "d.tif"), cv2.cvtColor(rgb16, cv2.COLOR_RGB2BGR))
    out, _, converted = load_image(tmp_path / "d.tif")
    assert converted and np.array_equal(out, rgb)


@pytest.mark.parametrize("orientation", range(1, 9))
def test_exif_orientation_matches_pil(tmp_path, orientation):
    rgb = _pattern(40, 70)
    img = Image.fromarray(rgb)
    exif = img.getexif()
    exif[0x0112] = orientation
    path = tmp_path / "o.png"
    img.save(path, exif=exif)
    out, _, converted = load_image(path)
    with Image.open(path) as ref:
        expected = np.asarray(ImageOps.exif_transpose(ref).convert("RGB"))
    assert np.array_equal(out, expected)
    assert converted == (orientation != 1)


def test_exif_focal_35mm_gives_pixels(tmp_path):
    img = Image.fromarray(_pattern(60, 80))
    exif = img.getexif()
    exif.get_ifd(0x8769)[0xA405] = 24  # 24 mm equivalent
    path = tmp_path / "f.jpg"
    img.save(path, exif=exif, quality=95)
    _, focal, _ = load_image(path)
    assert focal == pytest.approx(24 / 36 * 80)


def test_video_keeps_sharpest_frame_per_window(tmp_path):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (80, 60))
    base = cv2.cvtColor(_pattern(), cv2.COLOR_RGB2BGR)
    sharp_index = {0: 2, 1: 7}  # in each window of 5 frames, one sharp frame
    for k in range(10):
        frame = base if k in sharp_index.values() else cv2.GaussianBlur(base, (0, 0), 3)
        writer.write(frame)
    writer.release()
    frames = extract_video_frames(path, 2)
    assert [n for n, _ in frames] == ["clip_000002.png", "clip_000007.png"]
    cap = run_capture(path, CaptureOptions(video_frames=2), tmp_path / "out")
    assert cap.is_video and cap.names == ("clip_000002.png", "clip_000007.png")
    assert [f.size_wh for f in cap.frames] == [(80, 60)] * 2 and cap.read_images()[1].shape == (60, 80, 3)


def test_folder_capture_writes_images_and_flags_blur(tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    for k in range(4):
        img = _pattern(120, 160, seed=k)
        if k == 2:
            img = cv2.GaussianBlur(img, (0, 0), 6)
        Image.fromarray(img).save(src / f"im{k}.png")
    cap = run_capture(src, CaptureOptions(), tmp_path / "out")
    assert cap.names == ("im0.png", "im1.png", "im2.png", "im3.png")
    assert all((tmp_path / "out" / "images" / n).is_file() for n in cap.names)
    assert cap.quality.flagged("blur") == ["im2.png"]


def test_frames_hold_paths_and_read_back_the_loaded_pixels(tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    upright = Image.Exif()
    upright[0x0112] = 1  # EXIF that says "upright": the file is copied byte for byte, EXIF and all
    Image.fromarray(_pattern(60, 80, seed=1)).save(src / "a_copied.jpg", exif=upright, quality=95)
    rotated = Image.fromarray(_pattern(60, 80, seed=2))
    exif = rotated.getexif()
    exif[0x0112] = 6  # rotate 90 degrees clockwise on display: converted, written upright without EXIF
    rotated.save(src / "b_rotated.png", exif=exif)
    cap = run_capture(src, CaptureOptions(), tmp_path / "out")
    copied, turned = cap.frames
    assert copied.path.read_bytes() == (src / "a_copied.jpg").read_bytes()
    assert copied.size_wh == (80, 60) and turned.size_wh == (60, 80)
    assert np.array_equal(copied.read_rgb(), load_image(src / "a_copied.jpg")[0])
    assert np.array_equal(turned.read_rgb(), load_image(src / "b_rotated.png")[0])  # rotated once, not twice
    assert [im.shape for im in cap.read_images([1, 0])] == [(80, 60, 3), (60, 80, 3)]
    assert len(pickle.dumps(cap)) < 4000  # names, paths, sizes and per-frame numbers: no pixels
    cv2.imwrite(str(turned.path), np.zeros((80, 80, 3), np.uint8))
    with pytest.raises(InputError, match="b_rotated.png .* is 80x80, expected 60x80"):
        turned.read_rgb()
    copied.path.unlink()
    with pytest.raises(InputError, match="cannot read frame a_copied.jpg"):
        copied.read_rgb()


def test_blur_is_told_from_faint_texture_and_exposure():
    sharp = [_pattern(120, 160, seed=k) for k in range(5)]
    images = [
        sharp[0],
        cv2.GaussianBlur(sharp[1], (0, 0), 3),  # blurred
        (sharp[2] * 0.4).astype(np.uint8),  # under-exposed, still sharp
        (sharp[3] * 0.03 + 120).astype(np.uint8),  # nearly uniform: little texture, not blur
        sharp[4],
    ]
    names = [f"{k}.png" for k in range(5)]
    measures = [measure_frame(img) for img in images]
    quality = assess_capture(names, measures)
    assert quality.flagged("blur") == ["1.png"]
    assert quality.flagged("texture") == ["3.png"]
    assert quality.flagged("exposure") == ["2.png"]
    assert quality.edge_sharpness[2] == pytest.approx(quality.edge_sharpness[0], rel=0.1)  # contrast-invariant
    assert quality.names == tuple(names) and quality.to_report()["edge_sharpness"][1] < 0.05


def test_bad_inputs_have_clear_messages(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="no images found"):
        run_capture(empty, CaptureOptions(), tmp_path / "o1")
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    Image.fromarray(_pattern()).save(mixed / "a.png")
    (mixed / "LICENSE").write_text("CC BY")  # a dataset's documentation is left out, not an error
    (mixed / "README.md").write_text("photos")
    (mixed / "notes.txt").write_text("hello")
    with pytest.raises(InputError, match="holds 1 file.*not images.*notes.txt") as err:
        run_capture(mixed, CaptureOptions(), tmp_path / "o2")
    assert "--skip-bad-images" in err.value.fix
    (mixed / "broken.jpg").write_bytes(b"\xff\xd8\xff\xe0 not really a jpeg")
    cap = run_capture(mixed, CaptureOptions(skip_bad_images=True), tmp_path / "o3")
    assert cap.names == ("a.png",) and {n for n, _ in cap.skipped} == {
        "notes.txt",
        "broken.jpg",
        "LICENSE",
        "README.md",
    }
    (mixed / "notes.txt").unlink()
    with pytest.raises(InputError, match="cannot decode image broken.jpg"):
        run_capture(mixed, CaptureOptions(), tmp_path / "o4")
    with pytest.raises(InputError, match="not found"):
        run_capture(tmp_path / "missing", CaptureOptions(), tmp_path / "o5")


def _chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    """A PNG's chunks as (type, whole chunk with length and CRC)."""
    out, at = [], 8
    while at < len(data):
        length = int.from_bytes(data[at : at + 4], "big")
        out.append((data[at + 4 : at + 8], data[at : at + 12 + length]))
        at += 12 + length
    return out


@pytest.mark.parametrize("late", [False, True])
def test_png_exif_is_found_before_or_after_the_image_data(tmp_path, late, monkeypatch):
    """The orientation of a PNG whose eXIf chunk comes before the image data or after it (PNG allows both; Pillow
    finds the late one only by decoding the image), and a PNG without EXIF read without decoding it (issue 40:
    Pillow's getexif decoded every PNG of a capture once more)."""
    img = Image.fromarray(_pattern(40, 60, seed=2))
    exif = img.getexif()
    exif[0x0112] = 6
    path = tmp_path / "rotated.png"
    img.save(path, exif=exif)
    chunks = _chunks(path.read_bytes())
    assert b"eXIf" in [kind for kind, _ in chunks]
    if late:  # move eXIf to just before IEND
        moved = [c for c in chunks if c[0] == b"eXIf"]
        rest = [c for c in chunks if c[0] != b"eXIf"]
        chunks = rest[:-1] + moved + rest[-1:]
        path.write_bytes(b"\x89PNG\r\n\x1a\n" + b"".join(c for _, c in chunks))
    assert read_exif(path)[0] == 6
    plain = tmp_path / "plain.png"
    img.save(plain)
    decoded = []
    monkeypatch.setattr(PngImagePlugin.PngImageFile, "load", lambda self: decoded.append(1))
    assert read_exif(plain)[0] == 1 and not decoded


def test_frames_on_demand_keep_the_first_frames_that_fit(tmp_path, monkeypatch):
    """With a byte budget, the frames read first are kept (read-only) and served again without reading; those
    beyond the budget are read each time (issue 40: the feed-forward stage read every photo twice)."""
    src = tmp_path / "src"
    src.mkdir()
    for k in range(4):
        Image.fromarray(_pattern(60, 80, seed=k)).save(src / f"f{k}.png")
    capture = run_capture(src, CaptureOptions(), tmp_path / "out")
    reads = []
    real = type(capture.frames[0]).read_rgb
    monkeypatch.setattr(type(capture.frames[0]), "read_rgb", lambda self: reads.append(self.name) or real(self))
    frames = capture.frames_on_demand(keep_bytes=2 * 60 * 80 * 3)
    first = [frames[k] for k in range(4)]
    again = [frames[k] for k in range(4)] + frames[1:3]
    assert reads == ["f0.png", "f1.png", "f2.png", "f3.png", "f2.png", "f3.png", "f2.png"]
    assert again[0] is first[0] and not first[0].flags.writeable and first[2].flags.writeable
    assert all(np.array_equal(a, b) for a, b in zip(first, again))
    assert [f.name for f in capture.frames] == ["f0.png", "f1.png", "f2.png", "f3.png"]
    unkept = capture.frames_on_demand()
    unkept[0], unkept[0]
    assert reads[-2:] == ["f0.png", "f0.png"]
