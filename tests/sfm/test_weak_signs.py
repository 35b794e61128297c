"""Two weak signs agreeing contradict a frame nothing else checks (issue 39; in ``sfm.verify.unmatched``:
``_set_aside_misfits``, ``_depth_doubted``, the ``doubted`` clause of ``_photometric``).

Neither a poor photometric fit (a good frame the neighbours cover in part fits poorly) nor depth agreeing less than
most frames' (good frames down to 0.44 of the median) is enough alone; both together are. These scenes are the sweep's
families with every frame at the model's camera (as when the refinement is set aside), on seeds the thresholds were
not set on (they were set on 201-263)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ffrecon.sfm.verify.photometric import PhotometricOptions
from ffrecon.sfm.verify.signs import _depth_doubted, _depth_shares
from ffrecon.sfm.verify.unmatched import _set_aside_misfits
from ffrecon.sfm.verify.verdicts import CameraEvidence, CameraStatus, EvidenceOptions
from ffrecon.synthetic import CameraPath, SceneOptions, Texture, make_scene
from ffrecon.synthetic.layouts import Layout
from ffrecon.synthetic.simulated_model import SimulationOptions, prediction_from_truth, simulate

LUND = Path(__file__).resolve().parents[3] / "shared" / "data" / "lund"
WHY = "the refinement is set aside: every frame keeps the model's camera"


def _judge(layout: Layout, texture: Texture, seed: int, bad: tuple[int, ...]):
    options = SceneOptions(
        num_frames=8,
        width=320,
        height=240,
        seed=seed,
        path=CameraPath.WIDE,
        layout=layout,
        texture=texture,
        step_deg=(30.0, 50.0),
        fov_x_deg=70.0 if layout is Layout.ROOM else 65.0,
        photo_dir=str(LUND),
    )
    scene = make_scene(options)
    sim = SimulationOptions(seed=seed, bad_frames=bad, bad_rotation_deg=25.0)
    truth, _ = simulate(scene, sim)
    prediction = prediction_from_truth(scene, truth, sim)
    per_image = tuple(CameraEvidence(n, CameraStatus.UNCHECKED, WHY, 30.0) for n in scene.names)
    shares = _depth_shares(per_image, prediction, 10.0, every=True)
    doubted = _depth_doubted(shares, EvidenceOptions())
    photos = [np.asarray(im) for im in scene.images]
    judged = _set_aside_misfits(
        per_image, prediction.cam_from_world, photos.__getitem__, prediction, PhotometricOptions(), doubted
    )
    return [k for k, e in enumerate(judged) if not e.status.kept], judged


def test_a_frame_25_deg_off_is_often_left_out_and_good_frames_never():
    """Six seeds per family (11-16), textures and the bad frame drawn by seed. Measured: the bad frame left out in 3
    of 6 streets and 3 of 6 objects, no room (seen from inside, its frames overlap too little for the depth to tell);
    no good frame of 126."""
    caught, good_out = {layout: [] for layout in Layout}, []
    for layout in (Layout.STREET, Layout.OBJECT, Layout.ROOM):
        for seed in range(11, 17):
            bad = [1, 6][seed % 2]
            texture = [Texture.REPEATED, Texture.PHOTOS, Texture.PHOTOS_PLAIN_WALLS][seed % 3]
            out, judged = _judge(layout, texture, seed, (bad,))
            caught[layout] += [seed] if bad in out else []
            good_out += [(layout.value, seed, k) for k in out if k != bad]
            assert all(judged[k].status is CameraStatus.PHOTO_MISFIT and "depth" in judged[k].why for k in out)
    assert good_out == []
    assert len(caught[Layout.STREET]) >= 2 and len(caught[Layout.OBJECT]) >= 2, caught
