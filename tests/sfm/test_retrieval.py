"""Issue 25: sequential pairing without a model or a vocabulary tree still closes loops, by VLAD over SIFT."""

import numpy as np

from ffrecon.geometry.metrics import pose_errors
from ffrecon.sfm.crosscheck.options import ColmapOptions, PairingMode
from ffrecon.sfm.crosscheck.run import run_colmap
from ffrecon.synthetic import SceneOptions, make_scene
from ffrecon.synthetic.scene import write_scene


def test_sequential_pairing_adds_true_loop_candidates(tmp_path):
    """A full orbit of 48 frames (7.5 deg apart): sequential matching never pairs the last frames with the
    first; retrieval finds such pairs, and each one it adds is a real revisit (within 45 deg on the orbit)."""
    n = 48
    scene = make_scene(SceneOptions(num_frames=n, width=224, height=168, seed=2))
    images = write_scene(scene, tmp_path / "scene")
    result = run_colmap(
        images, scene.names, ColmapOptions(pairing=PairingMode.SEQUENTIAL), tmp_path / "colmap", focal_prior_px=None
    )
    lines = (tmp_path / "colmap" / "loop_pairs.txt").read_text().splitlines()
    index = {name: k for k, name in enumerate(scene.names)}
    pairs = np.array([[index[a] for a in line.split()] for line in lines])
    assert len(pairs) == result.features.num_loop_candidates >= 3
    gap = np.abs(pairs[:, 0] - pairs[:, 1])
    assert gap.min() >= 30, "nearer pairs are sequential matching's"
    degrees_apart = np.minimum(gap, n - gap) * 360 / n
    assert degrees_apart.max() <= 45, f"a candidate that is no revisit: {degrees_apart.max():.0f} deg apart"
    assert result.registered.all()
    assert pose_errors(result.cam_from_world, scene.cam_from_world).auc[5] > 0.95
