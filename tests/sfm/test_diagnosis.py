"""Why registration failed, from the images COLMAP left out: their own verified matches and the
triangulation angles of their verified pairs (issue 21). Small angles with many matches is small
parallax; few matches for the images left out is too little overlap or too wide a baseline."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from ffrecon.capture.quality import assess_capture, measure_frame
from ffrecon.errors import InputError
from ffrecon.geometry.poses import camera_centers
from ffrecon.pipeline import RunOptions, run
from ffrecon.sfm.crosscheck.gate_types import FailureCause, GateOptions
from ffrecon.sfm.crosscheck.registration import diagnose_registration, registration_gate
from ffrecon.sfm.verified_pairs import ImagePairs, read_image_pairs
from ffrecon.splat.stage import SplatOptions
from ffrecon.synthetic import CameraPath, SceneOptions, Texture, make_scene, write_scene
from ffrecon.synthetic.scene import LOOK_TARGET, PLAIN_SURFACES, _surface_textures, scene_geometry

# Eight photos 30 to 60 degrees apart around the objects, two walls and the ceiling near-uniform. Plain
# COLMAP (no focal prior: PNGs carry no EXIF) registers 3 of 8 (frames 4-6), as it does with the true focal.
WIDE = SceneOptions(num_frames=8, width=320, height=240, path=CameraPath.WIDE, texture=Texture.PLAIN_WALLS, seed=3)
LUND = Path(__file__).resolve().parents[3] / "shared" / "data" / "lund"
PARALLAX, OVERLAP = FailureCause.SMALL_PARALLAX, FailureCause.OVERLAP


def _pairs(name: str, inliers: list[int], angles_deg: list[float]) -> ImagePairs:
    return ImagePairs(name, np.array(inliers, int), np.array(angles_deg, np.float64))


def _diagnose(left_out, **kwargs) -> tuple[FailureCause, ...]:
    return diagnose_registration(
        None, ["a.jpg"], 1000, kwargs.pop("options", GateOptions()), left_out=left_out, **kwargs
    )


# ---------------------------------------------------------------- the rule, on constructed evidence


def test_many_matches_at_small_angles_is_small_parallax():
    walk = [_pairs("01.jpg", [172, 71], [0.5, 0.4]), _pairs("02.jpg", [265, 172], [1.3, 0.5])]
    assert _diagnose(walk) == (PARALLAX,)
    # No relative pose from a well-matched pair (turning on the spot): no parallax either.
    assert _diagnose([_pairs("01.jpg", [400], [np.nan])]) == (PARALLAX,)
    # The angle that counts is the median over the well-matched pairs, not the widest (one stray pair).
    assert _diagnose([_pairs("04.jpg", [348, 274, 124], [5.5, 2.6, 0.1])]) == (PARALLAX,)


def test_few_matches_for_the_images_left_out_is_overlap_or_wide_baseline_whatever_the_rest_share():
    # The bug this replaces: the median over all images (here 1,528, the registered ones matching well)
    # said "small parallax"; each image left out shares only 3 to 14 matches with any neighbour.
    left_out = [_pairs(f"{k}.png", [14, 9, 3], [38.0, 44.0, 51.0]) for k in range(4)]
    assert _diagnose(left_out, median_verified_matches=1528) == (OVERLAP,)
    # Few matches are few at any angle, and an image without any verified pair shares none.
    assert _diagnose([_pairs("a.png", [99], [0.2]), _pairs("b.png", [], [])]) == (OVERLAP,)


def test_each_image_left_out_votes_and_a_cause_needs_its_share():
    mixed = [_pairs("a", [300], [1.0]), _pairs("b", [300], [1.2])] + [_pairs(c, [20], [40.0]) for c in "cde"]
    assert _diagnose(mixed) == (OVERLAP, PARALLAX)  # 3 and 2 of 5 votes, both >= 30%; more votes first
    assert _diagnose(mixed, options=GateOptions(cause_share=0.5)) == (OVERLAP,)
    # Well matched with parallax explains nothing: another cause stands alone, else the fallback.
    wide_island = [_pairs("a", [257], [10.3]), _pairs("b", [257], [10.3])]
    assert _diagnose(wide_island, num_models=2) == (FailureCause.DISCONNECTED,)
    assert _diagnose(wide_island) == (OVERLAP,)
    assert _diagnose(wide_island, options=GateOptions(small_parallax_deg=12.0)) == (PARALLAX,)
    assert _diagnose([_pairs("a", [150], [3.0])], options=GateOptions(overlap_matches=200)) == (OVERLAP,)


def test_capture_flags_still_come_first():
    scene = make_scene(SceneOptions(num_frames=4, width=160, height=120, texture=Texture.TEXTURELESS))
    quality = assess_capture(scene.names, [measure_frame(img) for img in scene.images])
    walk = [_pairs(n, [300], [0.5]) for n in scene.names]
    assert diagnose_registration(quality, scene.names, 1000, GateOptions(), left_out=walk) == (FailureCause.TEXTURE,)


@pytest.mark.parametrize(
    "bad",
    [
        dict(small_parallax_deg=float("nan")),
        dict(small_parallax_deg=-1.0),
        dict(small_parallax_deg=181.0),
        dict(diagnosis_max_pairs=0),
        dict(diagnosis_max_images=2.5),
    ],
)
def test_thresholds_are_checked_where_they_are_made(bad):
    with pytest.raises(InputError, match=next(iter(bad))):
        GateOptions(**bad)


# ---------------------------------------------------------------- the wide-baseline synthetic scene


def test_the_wide_path_steps_30_to_60_degrees_with_plain_walls():
    scene = make_scene(dataclasses.replace(WIDE, width=96, height=72))
    centers = camera_centers(scene.cam_from_world)
    around = np.unwrap(np.arctan2(centers[:, 1], centers[:, 0]))
    assert np.all((np.degrees(np.diff(around)) >= 30) & (np.degrees(np.diff(around)) <= 60))
    axis = scene.cam_from_world[:, 2, :3]  # each camera looks at the objects
    to_target = (LOOK_TARGET - centers) / np.linalg.norm(LOOK_TARGET - centers, axis=1, keepdims=True)
    np.testing.assert_allclose(np.sum(axis * to_target, axis=1), 1.0, atol=1e-9)
    assert np.array_equal(make_scene(dataclasses.replace(WIDE, width=96, height=72)).images, scene.images)
    # The plain surfaces are near-uniform, the others are not.
    textures, _ = _surface_textures(scene_geometry(), Texture.PLAIN_WALLS, np.random.default_rng(0))
    spread = [float(t.reshape(-1, 3).std(axis=0).max()) for t in textures[:6]]
    assert all((spread[k] < 0.01) == (k in PLAIN_SURFACES) for k in range(6)), spread


@pytest.fixture(scope="module")
def wide_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("wide")
    image_dir = write_scene(make_scene(WIDE), root / "scene")
    return run(image_dir, root / "out", None, RunOptions(splat=SplatOptions(enabled=False)))


def test_the_wide_scene_without_a_model_names_overlap_or_wide_baseline_not_parallax(wide_run):
    colmap, gate = wide_run.colmap, wide_run.gates.verdicts[0]
    assert wide_run.exit_code == 5 and gate.name == "registration" and gate.failed
    assert colmap.num_registered < len(colmap.names) / 2  # measured: 3 of 8
    assert gate.causes == (OVERLAP,) and PARALLAX not in gate.causes
    assert "too wide a baseline" in gate.reason and "too wide a baseline" in gate.fix
    # The images left out share few matches with any neighbour (measured best: 26, 71, 158, 158, 26) ...
    left = [n for n, done in zip(colmap.names, colmap.registered) if not done]
    pairs = read_image_pairs(colmap.database_path, left)
    assert np.median([p.best_inliers for p in pairs]) < GateOptions().overlap_matches
    # ... and the pairs they have are wide (measured 25.7 to 71 deg), never a small-parallax pair.
    angles = np.concatenate([p.tri_angle_deg for p in pairs])
    assert np.nanmin(angles) > GateOptions().small_parallax_deg
    # Over all images the median was >= 100 (the registered ones match well): the old rule said parallax.
    assert np.median(colmap.features.num_inlier_matches) >= GateOptions().overlap_matches


def test_without_the_database_the_images_left_out_still_decide(wide_run, tmp_path):
    colmap = dataclasses.replace(wide_run.colmap, database_path=tmp_path / "gone.db")
    gate = registration_gate(colmap, GateOptions())
    assert gate.causes == (OVERLAP,) and "per verified pair" in gate.reason


# ---------------------------------------------------------------- lund: a forward walk, real photos


@pytest.fixture(scope="module")
def lund_photos(tmp_path_factory) -> Path:
    """The walk's first twelve photos at 640 px without EXIF (no focal prior)."""
    if len(list(LUND.glob("*.jpg"))) < 12:
        pytest.skip(f"the real capture is not at {LUND}")
    out = tmp_path_factory.mktemp("lund12")
    for k in range(1, 13):
        with Image.open(LUND / f"{k:02d}.jpg") as im:
            im.thumbnail((640, 640), Image.Resampling.LANCZOS)
            im.save(out / f"{k:02d}.jpg", quality=95)  # no EXIF
    return out


# Measured without EXIF: 01-04 registers none (median best neighbour 267 matches, 0.7 deg), 07-12 none
# (263, 0.9 deg); the diagnosis named small parallax in every failing subset tried (01-02 to 01-06, 07-12,
# once or twice JPEG-encoded), while 01-06 and 02-07 sometimes register in full.
@pytest.mark.parametrize("first, last", [(1, 4), (7, 12)])
def test_lunds_forward_walk_still_names_small_parallax(lund_photos, first, last, tmp_path):
    walk = tmp_path / "walk"
    walk.mkdir()
    for k in range(first, last + 1):
        (walk / f"{k:02d}.jpg").write_bytes((lund_photos / f"{k:02d}.jpg").read_bytes())
    result = run(walk, tmp_path / "out", None, RunOptions(splat=SplatOptions(enabled=False)))
    colmap, gate = result.colmap, result.gates.verdicts[0]
    assert gate.name == "registration" and gate.failed
    assert gate.causes == (PARALLAX,) and "too wide a baseline" not in gate.fix
    # Hundreds of verified matches with the next photo, at about a degree.
    left = [n for n, done in zip(colmap.names, colmap.registered) if not done]
    pairs = read_image_pairs(colmap.database_path, left)
    assert np.median([p.best_inliers for p in pairs]) >= GateOptions().overlap_matches
    assert np.nanmedian([p.tri_angle_deg[0] for p in pairs]) < 2.5
