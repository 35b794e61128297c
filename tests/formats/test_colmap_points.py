"""``reconstruction_from_cameras``'s points (issue 40: added through pycolmap's PLY import, not one call per point;
COLMAP's reader keeps float32 coordinates)."""

from __future__ import annotations

import numpy as np
import pycolmap

from ffrecon.colmap_io import reconstruction_from_cameras
from ffrecon.types import PinholeCamera


def test_points_keep_their_order_position_colour_and_an_empty_track_of_their_own():
    rng = np.random.default_rng(3)
    xyz, rgb = rng.normal(size=(50, 3)), rng.random((50, 3)).astype(np.float32)
    poses = np.tile(np.eye(3, 4), (2, 1, 1))
    rec = reconstruction_from_cameras(
        ["a.png", "b.png"], poses, [PinholeCamera(64, 48, 50.0, 50.0, 32.0, 24.0)] * 2, xyz, rgb
    )
    assert sorted(rec.points3D) == list(range(1, 51))
    got = np.array([rec.points3D[k].xyz for k in range(1, 51)])
    colours = np.array([rec.points3D[k].color for k in range(1, 51)])
    assert np.array_equal(got, xyz.astype(np.float32)) and got.dtype == np.float64
    assert np.array_equal(colours, np.clip(np.round(rgb * 255), 0, 255).astype(np.uint8))
    assert all(p.track.length() == 0 for p in rec.points3D.values())
    rec.points3D[1].track.add_element(1, 0)  # each point's track is its own copy, not one shared object
    assert rec.points3D[1].track.length() == 1 and rec.points3D[2].track.length() == 0
    assert isinstance(rec, pycolmap.Reconstruction) and rec.num_images() == 2
