"""Masks (``--masks``): a moving object painted into half the frames, masked there, leaves no trace.

A red disc moves across the even frames of the 12-frame demo scene (the simulated model's depth does not
see it: without masks its colour lands on the background). With masks over it (odd frames have no mask
file: used whole): no SIFT keypoint, fused point or splat Gaussian is red, transforms.json names each mask,
and the splat's held-out PSNR on the static pixels is not lower than that of the same scene without the disc.
"""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import open3d as o3d
import pycolmap
import pytest

from ffrecon.capture import CaptureOptions
from ffrecon.formats.splat_ply import read_splat_ply
from ffrecon.pipeline import RunOptions, run
from ffrecon.splat.optimize import OptimizeOptions
from ffrecon.splat.stage import SplatOptions

RADIUS = 28  # px, on 320x240 frames
RED = (255, 0, 0)
SH_C0 = 0.28209479177387814  # the DC term's constant: colour = 0.5 + SH_C0 * f_dc


def _disc(k: int, shape: tuple[int, int], grow: int = 0) -> np.ndarray:
    """``[H, W]`` bool: the disc of frame ``k`` (it moves 20 px a frame), ``grow`` px wider."""
    h, w = shape
    yy, xx = np.mgrid[:h, :w]
    cx, cy = 60 + 20 * k, 100 + 4 * k
    return (xx - cx) ** 2 + (yy - cy) ** 2 <= (RADIUS + grow) ** 2


@pytest.fixture(scope="module")
def folders(demo12, tmp_path_factory):
    """``(clean photos, photos with the disc, masks)``: the disc in the even frames, masked there."""
    root = tmp_path_factory.mktemp("masks")
    clean, painted, masks = root / "clean", root / "painted", root / "masks"
    for folder in (clean, painted, masks):
        folder.mkdir()
    for k, path in enumerate(sorted(demo12.images.iterdir())):
        shutil.copy(path, clean / path.name)
        rgb = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
        if k % 2 == 0:
            rgb[_disc(k, rgb.shape[:2])] = RED
            keep = ~_disc(k, rgb.shape[:2], grow=2)
            cv2.imwrite(str(masks / f"{path.stem}.png"), np.where(keep, 255, 0).astype(np.uint8))  # nerfstudio's name
        cv2.imwrite(str(painted / path.name), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    return clean, painted, masks


def _run(images, out, model, scene_dir, masks=None):
    optimize = OptimizeOptions.brief(iterations=300, max_seconds=1e6, progress=False)
    splat = SplatOptions(optimize=optimize, video=False)
    options = RunOptions(capture=CaptureOptions(masks=masks), splat=splat, ground_truth=scene_dir)
    result = run(images, out, model, options)
    assert result.exit_code == 0
    return result


def _red(rgb: np.ndarray) -> np.ndarray:
    """The disc's colour (pure red; the scene's own textures have a few such points and Gaussians too, which
    the clean run counts)."""
    return (rgb[:, 0] > 0.9) & (rgb[:, 1] < 0.1) & (rgb[:, 2] < 0.1)


def _red_gaussians(path) -> int:
    g = read_splat_ply(path)
    colour = 0.5 + SH_C0 * np.asarray(g.sh[:, 0, :], np.float64)  # [M, 3] DC colour
    opaque = 1 / (1 + np.exp(-np.asarray(g.opacity_logits, np.float64))) > 0.1
    return int((_red(colour) & opaque).sum())


@pytest.fixture(scope="module")
def runs(folders, demo12, tmp_path_factory):
    clean, painted, masks = folders
    root = tmp_path_factory.mktemp("mask-runs")
    return {
        "masked": _run(painted, root / "masked", demo12.model, demo12.scene_dir, masks),
        "unmasked": _run(painted, root / "unmasked", demo12.model, demo12.scene_dir),
        "clean": _run(clean, root / "clean", demo12.model, demo12.scene_dir, masks),
    }


def test_no_point_or_gaussian_on_the_masked_object(runs):
    points = {k: np.asarray(o3d.io.read_point_cloud(str(r.out_dir / "points.ply")).colors) for k, r in runs.items()}
    red = {k: int(_red(p).sum()) for k, p in points.items()}
    assert red["unmasked"] > 100 and red["masked"] <= red["clean"], red  # the control has the disc in its cloud
    gaussians = {k: _red_gaussians(r.splat.ply_path) for k, r in runs.items()}
    assert gaussians["unmasked"] > gaussians["clean"] + 50 and gaussians["masked"] <= gaussians["clean"] + 5, gaussians


def test_no_keypoint_on_the_masked_object(runs, folders):
    database = pycolmap.Database.open(str(runs["masked"].out_dir / "crosscheck" / "database.db"))
    try:
        for image in database.read_all_images():
            k = int(image.name.split("_")[1].split(".")[0])
            xy = database.read_keypoints(image.image_id)[:, :2]
            if k % 2 == 0:
                inside = _disc(k, (240, 320))[
                    np.clip(xy[:, 1].astype(int), 0, 239), np.clip(xy[:, 0].astype(int), 0, 319)
                ]
                assert len(xy) > 100 and not inside.any(), image.name
    finally:
        database.close()


def test_transforms_json_names_every_mask(runs):
    out = runs["masked"].out_dir
    frames = json.loads((out / "transforms.json").read_text())["frames"]
    assert all((out / f["mask_path"]).is_file() for f in frames)
    odd = cv2.imread(str(out / frames[1]["mask_path"]), cv2.IMREAD_GRAYSCALE)
    assert (odd == 255).all()  # no mask given for the odd frames: used whole


def test_the_static_part_scores_as_without_the_object(runs):
    masked = runs["masked"].splat.mean("psnr_cleaned")
    clean = runs["clean"].splat.mean("psnr_cleaned")  # the same masks, the scene without the disc
    assert masked >= clean - 0.3, (masked, clean)
