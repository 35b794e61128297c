"""Strict decoding (truncated and corrupt files, broken links), the size cap, option checks, write failures."""

import errno
import math
import shutil

import cv2
import numpy as np
import pytest
from PIL import Image

from ffrecon import cli
from ffrecon.capture import CaptureOptions, run_capture
from ffrecon.capture.images import load_image, load_photo
from ffrecon.capture.video import extract_video_frames
from ffrecon.errors import InputError, ResourceError


def _photo(h=240, w=320, seed=0):
    """A photo-like RGB image: smooth random texture with fine detail."""
    rng = np.random.default_rng(seed)
    base = cv2.resize(rng.integers(0, 255, (h // 8, w // 8, 3), dtype=np.uint8), (w, h), interpolation=cv2.INTER_CUBIC)
    return np.clip(base.astype(int) + rng.integers(-20, 20, (h, w, 3)), 0, 255).astype(np.uint8)


def _folder(tmp_path, count=3):
    src = tmp_path / "in"
    src.mkdir()
    for k in range(count):
        Image.fromarray(_photo(seed=k)).save(src / f"im{k}.jpg", quality=90)
    return src


def _cut_in_half(path):
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def test_truncated_jpeg_is_refused_naming_it_and_skipped_on_request(tmp_path):
    src = _folder(tmp_path)
    _cut_in_half(src / "im1.jpg")
    assert cv2.imread(str(src / "im1.jpg")) is not None  # OpenCV alone fills the missing half grey
    with pytest.raises(InputError, match="im1.jpg is truncated or corrupt: image file is truncated") as err:
        run_capture(src, CaptureOptions(), tmp_path / "o1")
    assert "--skip-bad-images" in err.value.fix and err.value.exit_code == 2
    cap = run_capture(src, CaptureOptions(skip_bad_images=True), tmp_path / "o2")
    assert cap.names == ("im0.jpg", "im2.jpg")
    assert [n for n, _ in cap.skipped] == ["im1.jpg"] and "truncated" in cap.skipped[0][1]
    assert cap.to_report()["skipped"][0]["name"] == "im1.jpg"
    assert not (tmp_path / "o2" / "images" / "im1.jpg").exists()


def test_every_bad_file_is_named_in_one_error(tmp_path):
    src = _folder(tmp_path, count=4)
    _cut_in_half(src / "im0.jpg")
    _cut_in_half(src / "im3.jpg")
    (src / "notes.txt").write_text("hello")
    with pytest.raises(InputError) as err:
        run_capture(src, CaptureOptions(), tmp_path / "o")
    said = err.value.problem
    assert said.startswith("3 input files cannot be used") and all(n in said for n in ("im0", "im3", "notes.txt"))


def _png_chunks(data: bytes):
    """(offset, type, length) of each chunk of a PNG file."""
    pos, chunks = 8, []
    while pos < len(data):
        length = int.from_bytes(data[pos : pos + 4], "big")
        chunks.append((pos, data[pos + 4 : pos + 8], length))
        pos += 12 + length
    return chunks


@pytest.mark.parametrize("damage", ["bad crc", "no IEND", "cut"])
def test_corrupt_png_is_refused(tmp_path, damage):
    src = _folder(tmp_path, count=2)
    path = src / "broken.png"
    cv2.imwrite(str(path), _photo(seed=5))
    data = bytearray(path.read_bytes())
    if damage == "bad crc":
        pos, _, length = next(c for c in _png_chunks(bytes(data)) if c[1] == b"IDAT")
        data[pos + 8 + length] ^= 0xFF  # the CRC only: the pixels themselves would still decode
    elif damage == "no IEND":
        data = data[:-12]
    else:
        data = data[: len(data) // 2]
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match="broken.png is truncated or corrupt"):
        load_photo(path)
    cap = run_capture(src, CaptureOptions(skip_bad_images=True), tmp_path / "o")
    assert cap.names == ("im0.jpg", "im1.jpg") and cap.skipped[0][0] == "broken.png"


@pytest.mark.parametrize("ext", [".tif", ".webp", ".bmp"])
def test_cut_tiff_webp_bmp_are_refused(tmp_path, ext):
    path = tmp_path / f"a{ext}"
    cv2.imwrite(str(path), _photo())
    _cut_in_half(path)
    with pytest.raises(InputError, match=f"a{ext}"):
        load_photo(path)


def test_dangling_link_is_reported(tmp_path):
    src = _folder(tmp_path)
    (src / "gone.jpg").symlink_to(tmp_path / "moved_away.jpg")
    with pytest.raises(InputError, match="gone.jpg is a symbolic link to .*moved_away.jpg, which does not exist"):
        run_capture(src, CaptureOptions(), tmp_path / "o1")
    cap = run_capture(src, CaptureOptions(skip_bad_images=True), tmp_path / "o2")
    assert len(cap.frames) == 3 and cap.skipped[0][0] == "gone.jpg"


def test_large_photo_is_capped_with_its_focal_prior(tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    img = Image.fromarray(_photo(2000, 3000))
    exif = img.getexif()
    exif.get_ifd(0x8769)[0xA405] = 24  # 24 mm equivalent: focal = 24 / 36 x long side
    img.save(src / "big.jpg", exif=exif, quality=90)
    Image.fromarray(_photo(seed=1)).save(src / "small.jpg", quality=90)
    cap = run_capture(src, CaptureOptions(), tmp_path / "o")
    big, small = cap.frames
    assert big.size_wh == (1600, 1067) and small.size_wh == (320, 240)
    assert big.focal_prior_px == pytest.approx(24 / 36 * 1600)
    assert cv2.imread(str(big.path)).shape == (1067, 1600, 3)  # images/ holds the capped frame
    assert small.path.read_bytes() == (src / "small.jpg").read_bytes()  # under the cap: copied as is
    report = cap.to_report()
    assert report["original_sizes_wh"] == [[3000, 2000], [320, 240]] and report["max_image_size"] == 1600
    assert report["scales"][0] == pytest.approx(1600 / 3000) and report["scales"][1] == 1.0
    full = run_capture(src, CaptureOptions(max_image_size=None), tmp_path / "o_full")
    assert full.frames[0].size_wh == (3000, 2000) and full.frames[0].focal_prior_px == pytest.approx(24 / 36 * 3000)
    assert CaptureOptions(max_image_size=0) == CaptureOptions(max_image_size=None)  # 0: full size, same key


def test_capped_pixels_are_the_area_average(tmp_path):
    rgb = _photo(900, 1200)
    path = tmp_path / "a.png"
    Image.fromarray(rgb).save(path)
    photo = load_photo(path, max_size=400)
    assert photo.rgb.shape == (300, 400, 3) and photo.converted and photo.scale == pytest.approx(1 / 3)
    assert np.array_equal(photo.rgb, cv2.resize(rgb, (400, 300), interpolation=cv2.INTER_AREA))
    # EXIF orientation: the cap applies to the upright long side, and the frame is upright.
    img = Image.fromarray(rgb)
    exif = img.getexif()
    exif[0x0112] = 6
    img.save(tmp_path / "r.png", exif=exif)
    turned = load_photo(tmp_path / "r.png", max_size=400)
    assert turned.rgb.shape == (400, 300, 3) and turned.original_size_wh == (900, 1200)
    assert np.abs(turned.rgb.astype(int) - np.rot90(photo.rgb, -1).astype(int)).max() <= 1


def test_16bit_and_rgba_above_the_cap(tmp_path):
    rgb = _photo(600, 800)
    cv2.imwrite(str(tmp_path / "d.png"), cv2.cvtColor(rgb.astype(np.uint16) * 257, cv2.COLOR_RGB2BGR))
    photo = load_photo(tmp_path / "d.png", max_size=200)
    assert photo.rgb.dtype == np.uint8 and photo.rgb.shape == (150, 200, 3)
    assert np.abs(photo.rgb.astype(int) - cv2.resize(rgb, (200, 150), interpolation=cv2.INTER_AREA)).max() <= 1
    rgba = np.dstack([rgb, np.full(rgb.shape[:2], 255, np.uint8)])
    rgba[:300, :, 3] = 0  # the top half transparent: white once composited
    Image.fromarray(rgba).save(tmp_path / "a.png")
    photo = load_photo(tmp_path / "a.png", max_size=200)
    assert photo.rgb.shape == (150, 200, 3) and np.all(photo.rgb[:70] == 255)
    assert np.array_equal(load_image(tmp_path / "a.png")[0][:300], np.full((300, 800, 3), 255, np.uint8))


@pytest.mark.parametrize(
    "options, flag",
    [
        ({"video_frames": -3}, "--video-frames"),
        ({"video_frames": 0}, "--video-frames"),
        ({"video_frames": math.nan}, "--video-frames"),
        ({"video_frames": 2.5}, "--video-frames"),
        ({"max_image_size": 10}, "--max-image-size"),
        ({"max_image_size": -1}, "--max-image-size"),
        ({"max_images": 0}, "max_images"),
    ],
)
def test_capture_options_are_checked_where_made(options, flag):
    with pytest.raises(InputError, match=flag) as err:
        CaptureOptions(**options)
    assert err.value.exit_code == 2 and err.value.fix


def test_a_frame_that_cannot_be_written_is_a_resource_error(tmp_path, monkeypatch):
    src = _folder(tmp_path, count=2)

    def disk_full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(shutil, "copyfile", disk_full)
    with pytest.raises(ResourceError, match="cannot write frame im0.jpg .*No space left on device") as err:
        run_capture(src, CaptureOptions(), tmp_path / "o1")
    assert err.value.exit_code == 6 and "disk" in err.value.fix
    monkeypatch.setattr(cv2, "imwrite", lambda *a, **k: False)  # how OpenCV reports a failed write
    with pytest.raises(ResourceError, match="cannot write frame"):
        run_capture(src, CaptureOptions(max_image_size=64), tmp_path / "o2")


def test_cli_truncated_jpeg_exits_2_with_one_message(tmp_path, capsys):
    src = _folder(tmp_path)
    _cut_in_half(src / "im2.jpg")
    code = cli.main(["run", str(src), "-o", str(tmp_path / "out"), "--no-splat", "-q"])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    assert err.startswith("ffrecon: error: im2.jpg is truncated or corrupt") and "fix:" in err
    code = cli.main(["run", str(src), "-o", str(tmp_path / "out"), "--video-frames", "-3", "-q"])
    assert code == 2 and "--video-frames (capture video_frames) must be a whole number >= 2" in capsys.readouterr().err


def test_a_short_video_says_why_it_gives_fewer_frames(tmp_path, caplog):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (80, 60))
    for k in range(5):
        writer.write(cv2.cvtColor(_photo(60, 80, seed=k), cv2.COLOR_RGB2BGR))
    writer.release()
    with caplog.at_level("WARNING", logger="ffrecon.capture"):
        frames = list(extract_video_frames(path, 8))
    assert len(frames) == 5 and "clip.avi has only 5 frames: keeping all of them, not 8" in caplog.text
