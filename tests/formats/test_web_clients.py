"""Web-ready splats (issue 11): splat.spz and SOG, opened in the clients people use.

- SPZ round trip through gsply, within SPZ's quantisation (ffrecon.formats.web states the steps).
- splat-transform (PlayCanvas) reads splat.ply and splat.spz with the count and bounds ffrecon wrote,
  and converts both to SOG, which it reads back.
- Spark (three.js, headless Chromium) renders splat.ply and splat.spz from a training camera; the
  picture must match ffrecon's own renderer (PSNR >= 25 dB). That is the proof of the conventions
  (OpenCV world and camera, wxyz quaternions, channel-major SH, logit opacity, log scales, pixel
  centres, colours untouched); copies in SPZ's nominal RUB frame or with colours stored as RGB
  instead of SH coefficients must fail it by a wide margin. The same splat with random higher SH
  bands checks the view-dependent colour, against a copy with f_rest in the wrong order.

Each client test is skipped, with the reason, when node, the npm clients or Chromium are missing.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
from pathlib import Path

import cv2
import gsply
import numpy as np
import pycolmap
import pytest
import torch

from ffrecon.formats.splat_ply import read_splat_ply, write_splat_ply
from ffrecon.formats.web import SPLAT_TRANSFORM_ENV, WebExportError, find_splat_transform, write_sog, write_splat_spz
from ffrecon.gaussians import Gaussians
from ffrecon.splat.optimize import OptimizeOptions
from ffrecon.splat.render import render_view
from ffrecon.types import PinholeCamera

SH_C0 = 0.28209479177387814
CLIENTS = Path(__file__).resolve().parents[2] / "clients"
MIN_PSNR = 25.0  # dB, Spark against ffrecon's renderer, same camera and size
NEGATIVE_MARGIN = 10.0  # dB: a splat in the wrong frame must score at least this much below the threshold


def _random_gaussians(n: int, degree: int, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    return Gaussians(
        means=(torch.rand(n, 3, generator=g) - 0.5) * 20.0,
        quats_wxyz=torch.randn(n, 4, generator=g),
        log_scales=torch.rand(n, 3, generator=g) * 8.0 - 7.0,
        opacity_logits=torch.randn(n, generator=g) * 3.0,
        sh=torch.cat(
            [torch.randn(n, 1, 3, generator=g), 0.3 * torch.randn(n, (degree + 1) ** 2 - 1, 3, generator=g)], 1
        ),
    )


def test_spz_round_trip_within_its_quantisation(tmp_path):
    """Write with ffrecon, read back with gsply: every attribute within the quantisation step."""
    g = _random_gaussians(2000, degree=3)
    path = write_splat_spz(tmp_path / "splat.spz", g)
    back = gsply.read_spz(path)
    assert len(back.means) == len(g)
    np.testing.assert_allclose(back.means, g.means.numpy(), rtol=0, atol=2.0**-13 + 1e-6)  # 12 fractional bits
    np.testing.assert_allclose(back.scales, g.log_scales.numpy(), rtol=0, atol=1 / 32 + 1e-5)
    opacity = torch.sigmoid(g.opacity_logits).numpy()
    np.testing.assert_allclose(1 / (1 + np.exp(-back.opacities)), opacity, rtol=0, atol=0.5 / 255 + 1e-5)
    dc = np.clip(g.sh[:, 0].numpy(), -0.5 / 0.15, 0.5 / 0.15)  # SPZ's colour byte holds +-3.33
    np.testing.assert_allclose(back.sh0, dc, rtol=0, atol=0.5 / (0.15 * 255) + 1e-5)
    rest = g.sh[:, 1:].numpy()
    np.testing.assert_allclose(back.shN, np.clip(rest, -1, 127 / 128), rtol=0, atol=1 / 256 + 1e-5)
    q = torch.nn.functional.normalize(g.quats_wxyz, dim=1).numpy()
    same_sign = np.sign(np.sum(q * back.quats, axis=1, keepdims=True))  # q and -q are one rotation
    np.testing.assert_allclose(back.quats * same_sign, q, rtol=0, atol=0.004)


def test_spz_keeps_large_scenes_with_fewer_fractional_bits(tmp_path):
    g = _random_gaussians(100, degree=0)
    g.means = g.means * 500.0  # +-5000 units: beyond 12 fractional bits' +-2048
    back = gsply.read_spz(write_splat_spz(tmp_path / "big.spz", g))
    np.testing.assert_allclose(back.means, g.means.numpy(), rtol=0, atol=2.0**-11 + 1e-3)  # 10 bits


def test_the_splat_stage_writes_spz_beside_ply(full_run):
    report = json.loads((full_run / "report.json").read_text())
    assert report["splat"]["splat_spz"] == "splat.spz"
    assert report["splat"]["splat_sog"] is None  # opt-in
    ply, spz = read_splat_ply(full_run / "splat.ply"), gsply.read_spz(full_run / "splat.spz")
    assert len(spz.means) == len(ply)
    assert (full_run / "splat.spz").stat().st_size < (full_run / "splat.ply").stat().st_size / 5


def test_sog_names_the_missing_converter_and_the_fix(tmp_path):
    with pytest.raises(WebExportError, match="not found") as err:
        write_sog(tmp_path / "a.ply", tmp_path / "a.sog", executable=tmp_path / "no-such-splat-transform")
    assert "make clients" in err.value.fix and SPLAT_TRANSFORM_ENV in err.value.fix


def test_sog_is_bounded_in_time(tmp_path):
    slow = tmp_path / "splat-transform"
    slow.write_text("#!/bin/sh\nsleep 30\n")
    slow.chmod(0o755)
    with pytest.raises(WebExportError, match="did not finish"):
        write_sog(tmp_path / "a.ply", tmp_path / "a.sog", executable=slow, timeout_s=0.5)
    assert not (tmp_path / "a.sog").exists()


def test_sog_reports_a_failing_converter(tmp_path):
    failing = tmp_path / "splat-transform"
    failing.write_text("#!/bin/sh\necho 'cannot parse input' >&2\nexit 3\n")
    failing.chmod(0o755)
    with pytest.raises(WebExportError, match="exit 3.*cannot parse input"):
        write_sog(tmp_path / "a.ply", tmp_path / "a.sog", executable=failing)


def test_the_converter_is_found_through_the_environment_first(tmp_path, monkeypatch):
    monkeypatch.setenv(SPLAT_TRANSFORM_ENV, str(tmp_path / "custom"))
    assert find_splat_transform() == tmp_path / "custom"


# --- splat-transform ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def splat_transform(node_clients) -> Path:
    exe = node_clients / ".bin" / "splat-transform"
    if not exe.exists():
        pytest.skip("clients/node_modules has no splat-transform: run `make clients`")
    return exe


def _splat_transform_json(exe: Path, path: Path, flag: str) -> dict:
    """``splat-transform -q PATH --stats|--info json null``: exit 0, nothing on stderr, JSON on stdout."""
    proc = subprocess.run(
        [str(exe), "-q", str(path), flag, "json", "null"], capture_output=True, text=True, timeout=120, check=False
    )
    assert proc.returncode == 0, f"splat-transform {flag} {path.name}: exit {proc.returncode}\n{proc.stderr}"
    assert proc.stderr.strip() == "", f"splat-transform complained about {path.name}:\n{proc.stderr}"
    return json.loads(proc.stdout)


@pytest.mark.parametrize(
    ("name", "tolerance"),
    [
        ("splat.ply", 1e-6),  # float32 as written; splat-transform prints 6 decimals
        ("splat.spz", 2.0**-13 + 1e-6),  # SPZ's 24-bit fixed point with 12 fractional bits, then printing
    ],
)
def test_splat_transform_reads_count_and_bounds(full_run, splat_transform, name, tolerance):
    ours = read_splat_ply(full_run / "splat.ply").means.numpy().astype(np.float64)
    info = _splat_transform_json(splat_transform, full_run / name, "--stats")
    assert info["numGaussians"] == len(ours)
    assert info["shBands"] == 3
    stats = info["stats"][0]
    for axis, column in enumerate("xyz"):
        i = stats["columns"].index(column)
        got = (stats["data"]["min"][i], stats["data"]["max"][i])
        want = (ours[:, axis].min(), ours[:, axis].max())
        tol = tolerance + 1e-6 * np.abs(want).max()
        assert np.allclose(got, want, rtol=0, atol=tol), f"{name} {column} bounds {got} != ffrecon's {want}"


@pytest.mark.parametrize("name", ["splat.ply", "splat.spz"])
def test_splat_transform_converts_to_sog(full_run, splat_transform, name, tmp_path):
    """The files the run wrote, whole, to SOG and back: 3-4 s each here, because the brief test splat's
    higher SH bands are still all zero; SOG's SH k-means on the CPU grows fast once they are not (see
    ffrecon.formats.web), which is why the test that writes SOG from the stage uses a small splat."""
    count = len(read_splat_ply(full_run / "splat.ply"))
    sog = write_sog(full_run / name, tmp_path / f"{name}.sog", executable=splat_transform, timeout_s=180)
    assert sog.stat().st_size > 0
    info = _splat_transform_json(splat_transform, sog, "--info")
    assert info["numGaussians"] == count
    assert info["format"] == "sog"


# --- Spark in headless Chromium -----------------------------------------------------------------


def _training_view(run_dir: Path) -> tuple[str, np.ndarray, PinholeCamera]:
    """A training frame's final camera from ``sparse/0``: name, ``cam_from_world [3, 4]``, intrinsics."""
    heldout = set(json.loads((run_dir / "report.json").read_text())["splat"]["heldout_views"])
    rec = pycolmap.Reconstruction(str(run_dir / "sparse" / "0"))
    image = next(im for _, im in sorted(rec.images.items()) if im.name not in heldout)
    cam = rec.cameras[image.camera_id]
    assert not np.any(cam.params[3:]), "the splat is trained on undistorted images: expected zero distortion"
    fx, fy = (cam.focal_length_x, cam.focal_length_y)
    pinhole = PinholeCamera(cam.width, cam.height, fx, fy, cam.principal_point_x, cam.principal_point_y)
    return image.name, image.cam_from_world().matrix(), pinhole


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / max(np.mean((a - b) ** 2), 1e-12)))


def _read_rgb(path: Path) -> np.ndarray:
    return cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB).astype(np.float64) / 255.0


def _render(g: Gaussians, cam_from_world: np.ndarray, camera: PinholeCamera, o: OptimizeOptions) -> np.ndarray:
    return render_view(g, cam_from_world, camera, background=o.background, raster=o.raster).numpy()


@pytest.fixture(scope="module")
def spark_scores(full_run, chromium, node_clients, tmp_path_factory) -> dict[str, float]:
    """PSNR (dB) of Spark's render of each file against ffrecon's render of splat.ply, one browser."""
    work = tmp_path_factory.mktemp("spark")
    name, cam_from_world, camera = _training_view(full_run)
    o = OptimizeOptions.brief()  # what the splat stage rendered and trained with
    g = read_splat_ply(full_run / "splat.ply")
    ours = _render(g, cam_from_world, camera, o)
    cv2.imwrite(str(work / "ffrecon.png"), cv2.cvtColor((ours * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR))
    # Negative controls: the SPZ in SPZ's nominal RUB frame, i.e. converted from the PLY's RDF as
    # Niantic's packer does when told the source frame (a 180-degree turn about x: y and z negated,
    # quaternion (w, x, -y, -z); the SH rest, all zero after the brief training, left alone); and
    # the PLY with colours stored as RGB instead of SH DC coefficients. (Opacity stored as a
    # probability instead of a logit is milder, 22 dB measured; scales stored as lengths instead of
    # logs fail too, 10 dB, but the huge Gaussians take SwiftShader 2 minutes; quaternions stored xyzw make a
    # weak control here: the brief training leaves most rotations near identity, which xyzw turns
    # by about 180 degrees about z, mapping an axis-aligned ellipsoid onto itself; measured 31 to 40 dB.)
    flip = torch.tensor([1.0, -1.0, -1.0])
    rub = Gaussians(
        g.means * flip, g.quats_wxyz * torch.tensor([1.0, 1.0, -1.0, -1.0]), g.log_scales, g.opacity_logits, g.sh
    )
    write_splat_spz(work / "frame_rub.spz", rub)
    # The higher SH bands: after the brief training they are all zero, so on their own the files above
    # say nothing about the SH basis or f_rest's channel-major order. The same splat with random view-
    # dependent colour (bands 1-3, sd 0.25 per coefficient: colours shift by tenths across the view)
    # must match ffrecon's render of it too; and its coefficients written coefficient-major
    # (r0 g0 b0 r1 ..., the classic mistake) must not.
    rng = np.random.default_rng(0)
    rest = torch.from_numpy(rng.normal(0.0, 0.25, size=tuple(g.sh[:, 1:].shape))).float()
    shiny = Gaussians(g.means, g.quats_wxyz, g.log_scales, g.opacity_logits, torch.cat([g.sh[:, :1], rest], 1))
    write_splat_ply(work / "sh.ply", shiny)
    refs = {"sh": _render(shiny, cam_from_world, camera, o)}
    bands = rest.shape[1]
    wrong = rest.reshape(len(g), bands * 3).reshape(len(g), 3, bands).transpose(1, 2)  # file order coefficient-major
    write_splat_ply(
        work / "sh_coefficient_major.ply", dataclasses.replace(shiny, sh=torch.cat([g.sh[:, :1], wrong], 1))
    )
    refs["sh_coefficient_major"] = refs["sh"]
    g.sh = torch.cat([g.sh[:, :1] * SH_C0 + 0.5, g.sh[:, 1:]], dim=1)
    write_splat_ply(work / "rgb_not_sh.ply", g)
    splats = {
        "ply": full_run / "splat.ply",
        "spz": full_run / "splat.spz",
        "frame_rub": work / "frame_rub.spz",
        "rgb_not_sh": work / "rgb_not_sh.ply",
        "sh": work / "sh.ply",
        "sh_coefficient_major": work / "sh_coefficient_major.ply",
    }
    job = {
        "chromium": str(chromium),
        "width": camera.width,
        "height": camera.height,
        **{k: getattr(camera, k) for k in ("fx", "fy", "cx", "cy")},
        "cam_from_world": np.asarray(cam_from_world).tolist(),
        "background": list(o.background),
        "eps2d": o.raster.eps2d,
        "renders": [{"splat": str(path), "out": str(work / f"spark_{key}.png")} for key, path in splats.items()],
    }
    (work / "job.json").write_text(json.dumps(job))
    proc = subprocess.run(
        ["node", str(CLIENTS / "spark_render.mjs"), str(work / "job.json")],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert proc.returncode == 0, f"Spark render failed:\n{proc.stdout}\n{proc.stderr}"
    for line in proc.stdout.splitlines():
        result = json.loads(line)
        assert result["problems"] == [], result["problems"]
        assert result["numSplats"] == len(g), result  # every Gaussian loaded
    scores = {}
    for key in splats:
        theirs = _read_rgb(work / f"spark_{key}.png")
        ref = refs.get(key, ours)
        assert theirs.shape == ref.shape, f"Spark's {key} image is {theirs.shape}, ffrecon's {ref.shape}"
        scores[key] = _psnr(theirs, ref)
    scores["sh_effect"] = _psnr(refs["sh"], ours)  # how much the random bands change ffrecon's own picture
    print(f"Spark vs ffrecon, {name}: " + ", ".join(f"{k} {v:.1f} dB" for k, v in scores.items()))
    return scores


@pytest.mark.slow
@pytest.mark.parametrize("key", ["ply", "spz"])
def test_spark_renders_what_ffrecon_renders(spark_scores, key):
    assert spark_scores[key] >= MIN_PSNR, f"Spark's render of splat.{key}: {spark_scores[key]:.1f} dB < {MIN_PSNR}"


@pytest.mark.slow
def test_spark_comparison_fails_for_an_spz_in_another_frame(spark_scores):
    """The frame mistake SPZ invites: converting the PLY's RDF to SPZ's nominal RUB puts the scene
    behind the camera for Spark (and splat-transform), which decode SPZ without conversion."""
    assert spark_scores["frame_rub"] < MIN_PSNR - NEGATIVE_MARGIN, spark_scores


@pytest.mark.slow
def test_spark_shows_the_view_dependent_colour_ffrecon_shows(spark_scores):
    """Random higher SH bands change ffrecon's picture well past the threshold (about 21 dB against the
    plain splat), and Spark reproduces the change (about 35 dB): the SH basis, its signs and f_rest's
    channel-major order agree. Not to within 1e-2 like the plain splat: Spark stores SH coefficients
    at reduced precision (the gap grows with their size: 28 dB at sd 0.4), so the check is relative."""
    assert spark_scores["sh"] >= MIN_PSNR, spark_scores
    assert spark_scores["sh"] - spark_scores["sh_effect"] >= NEGATIVE_MARGIN, spark_scores


@pytest.mark.slow
def test_spark_comparison_fails_for_sh_stored_coefficient_major(spark_scores):
    """The same coefficients in the wrong order in the file (measured about 19.5 dB, 15 below the right one)."""
    assert spark_scores["sh"] - spark_scores["sh_coefficient_major"] >= NEGATIVE_MARGIN, spark_scores


@pytest.mark.slow
def test_spark_comparison_fails_for_colours_stored_as_rgb(spark_scores):
    assert spark_scores["rgb_not_sh"] < MIN_PSNR - NEGATIVE_MARGIN, spark_scores


def _run_steps():
    """What the splat stage's steps share (its timer, a budget with room), for calling one step alone."""
    import time

    from ffrecon.splat.budget import StageBudget
    from ffrecon.splat.stage import _Run
    from ffrecon.timing import StageTimer

    return _Run(StageTimer(), StageBudget(60.0, time.perf_counter()))


def test_the_splat_stage_writes_sog_when_asked(splat_transform, tmp_path):
    from ffrecon.splat.stage import SplatOptions, _write_outputs

    g = _random_gaussians(500, degree=3)
    camera = PinholeCamera(64, 48, 50.0, 50.0, 32.0, 24.0)
    options = SplatOptions(video=False, sog=True)
    ply, video, web = _write_outputs(tmp_path, g, np.zeros((1, 3, 4)), camera, options, _run_steps())
    assert video is None and web["spz_path"] == tmp_path / "splat.spz"
    assert web["sog_path"] == tmp_path / "splat.sog"
    assert _splat_transform_json(splat_transform, web["sog_path"], "--info")["numGaussians"] == 500


def test_the_splat_stage_keeps_going_without_the_sog_converter(tmp_path, monkeypatch, caplog):
    from ffrecon.splat.stage import SplatOptions, _write_outputs

    monkeypatch.setenv(SPLAT_TRANSFORM_ENV, str(tmp_path / "no-such-splat-transform"))
    options = SplatOptions(video=False, sog=True)
    camera = PinholeCamera(64, 48, 50.0, 50.0, 32.0, 24.0)
    ply, _, web = _write_outputs(tmp_path, _random_gaussians(50, 0), np.zeros((1, 3, 4)), camera, options, _run_steps())
    assert ply.exists() and web["sog_path"] is None
    assert "splat.sog not written" in caplog.text and "make clients" in caplog.text
