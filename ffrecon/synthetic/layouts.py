"""Scene layouts beyond the objects-in-a-room scene: the families of issue 39's held-out wide-baseline tests.

Each layout is a closed axis-aligned room (the renderer ray-casts from inside one) holding boxes and
spheres, plus the wide-baseline camera path that suits it. They differ in what a sparse capture of them
looks like, so rules tuned on one do not carry over by accident:

- ``OBJECTS``: the original scene (a few objects in the middle of a 6 x 6 room, cameras around them,
  looking in). Its geometry lives in :mod:`ffrecon.synthetic.scene`.
- ``ROOM``: a furnished 8 x 6 room seen from inside: cameras wander near the middle and look *out* at
  the walls and the furniture along them, each view turning 30-60 degrees (by default) from the last.
  Most of each view is wall, so pairs share planar surfaces seen at a distance of 2-4 units.
- ``OBJECT``: one cluster of objects on a plinth in a large hall, orbited at 30-90 degree steps with
  the camera far (3 units) from a small subject: little of each view is shared background.
- ``STREET``: a facade (the wall at y = +4 of a long, tall street) with bay windows, a doorstep and a kiosk,
  photographed from the far pavement: each view's azimuth to the facade turns 20-40 degrees from the
  last (within 60 degrees of the facade's normal), so the shared surface is one big plane seen
  obliquely plus shallow relief.

All units are arbitrary (the simulated model normalises scale); world z is up.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from ffrecon.geometry.poses import look_at_cam_from_world
from ffrecon.synthetic.render import Box, Geometry, Sphere


class Layout(enum.Enum):
    OBJECTS = "objects"
    ROOM = "room"
    OBJECT = "object"
    STREET = "street"


@dataclass(frozen=True)
class LayoutSpec:
    """What :mod:`ffrecon.synthetic.scene` needs of a layout other than ``OBJECTS``."""

    geometry: Geometry
    step_deg: tuple[float, float]  # default turn between consecutive views of the wide path
    # Room faces (2 * axis + side) that Texture.PLAIN_WALLS leaves near-uniform.
    plain_surfaces: tuple[int, ...]


def _box(center, half, yaw_deg: float) -> Box:
    return Box(center=np.array(center, float), half_size=np.array(half, float), yaw_rad=np.radians(yaw_deg))


_ROOM = LayoutSpec(
    geometry=Geometry(
        room_lo=np.array([-4.0, -3.0, 0.0]),
        room_hi=np.array([4.0, 3.0, 2.8]),
        boxes=(
            _box([0.0, 2.55, 0.45], [1.1, 0.4, 0.45], 0),  # sofa against the +y wall
            _box([-3.6, 0.5, 0.9], [0.35, 0.9, 0.9], 0),  # shelf against the -x wall
            _box([3.55, -1.2, 0.5], [0.4, 0.6, 0.5], 0),  # cabinet against the +x wall
            _box([1.8, -2.6, 0.4], [0.7, 0.35, 0.4], 0),  # desk against the -y wall
            _box([-1.6, -1.8, 0.3], [0.4, 0.4, 0.3], 25),  # low table
        ),
        spheres=(Sphere(center=np.array([2.9, 2.3, 1.1]), radius=0.3),),
    ),
    step_deg=(30.0, 60.0),
    plain_surfaces=(1, 2, 5),  # two walls and the ceiling
)

_OBJECT = LayoutSpec(
    geometry=Geometry(
        room_lo=np.array([-7.0, -7.0, 0.0]),
        room_hi=np.array([7.0, 7.0, 4.0]),
        boxes=(
            _box([0.0, 0.0, 0.25], [0.6, 0.6, 0.25], 0),  # plinth
            _box([0.1, -0.05, 0.75], [0.25, 0.18, 0.25], 30),
            _box([-0.2, 0.25, 0.6], [0.12, 0.12, 0.1], -20),
        ),
        spheres=(Sphere(center=np.array([0.25, 0.28, 0.68]), radius=0.18),),
    ),
    step_deg=(30.0, 90.0),
    plain_surfaces=(0, 1, 2, 3, 5),  # every wall and the ceiling: only the object and the floor carry texture
)

_STREET = LayoutSpec(
    geometry=Geometry(
        room_lo=np.array([-14.0, -4.0, 0.0]),
        room_hi=np.array([14.0, 4.0, 9.0]),
        boxes=(
            _box([-3.0, 3.7, 3.2], [1.0, 0.3, 0.8], 0),  # bay windows
            _box([2.5, 3.7, 3.2], [1.0, 0.3, 0.8], 0),
            _box([-0.3, 3.6, 0.15], [1.4, 0.4, 0.15], 0),  # doorstep
            _box([5.5, 2.9, 0.7], [1.1, 0.5, 0.7], 5),  # a kiosk on the pavement
        ),
        spheres=(),
    ),
    step_deg=(20.0, 40.0),
    plain_surfaces=(0, 1, 2, 5),  # the street's ends, the opposite facade and the sky
)

_SPECS = {Layout.ROOM: _ROOM, Layout.OBJECT: _OBJECT, Layout.STREET: _STREET}


def layout_spec(layout: Layout) -> LayoutSpec:
    """The geometry and defaults of ``layout`` (not ``OBJECTS``, which :mod:`.scene` builds)."""
    return _SPECS[layout]


def wide_path(layout: Layout, num_frames: int, seed: int, step_deg: tuple[float, float]) -> np.ndarray:
    """``[N, 3, 4]`` cam_from_world (OpenCV) of a sparse capture of ``layout``: consecutive views turn
    ``step_deg`` (drawn from a stream of ``seed``'s own, so textures stay those of the seed)."""
    rng = np.random.default_rng([seed, 39])
    steps = np.radians(rng.uniform(*step_deg, size=max(num_frames - 1, 0)))
    turns = np.concatenate([[0.0], np.cumsum(steps)])
    if layout is Layout.ROOM:
        # Near the middle, looking out: the heading turns by the step, the position wanders 0.3-1.0 units.
        heading = turns + rng.uniform(0, 2 * np.pi)
        radius = rng.uniform(0.3, 1.0, num_frames)
        spot = rng.uniform(0, 2 * np.pi, num_frames)
        centers = np.stack([radius * np.cos(spot), 0.7 * radius * np.sin(spot), rng.uniform(1.2, 1.6, num_frames)], 1)
        look = np.stack([np.cos(heading), np.sin(heading), rng.uniform(-0.35, -0.05, num_frames)], 1)
        return np.stack([look_at_cam_from_world(c, c + d) for c, d in zip(centers, look)])
    if layout is Layout.OBJECT:
        angles = turns + rng.uniform(0, 2 * np.pi)
        radius = 3.0 * rng.uniform(0.9, 1.1, num_frames)
        centers = np.stack([radius * np.cos(angles), radius * np.sin(angles), rng.uniform(1.4, 2.2, num_frames)], 1)
        target = np.array([0.0, 0.0, 0.6])
        return np.stack([look_at_cam_from_world(c, target + rng.normal(0, 0.08, 3)) for c in centers])
    if layout is Layout.STREET:
        # From the far pavement (y about -3), each view aimed at a point of the facade (y = 4) at an azimuth
        # from its normal that walks by the step, reflected to stay within 60 degrees of it (a person
        # walking along and photographing the building from ever other angles, never from behind its plane).
        azimuth = np.empty(num_frames)
        azimuth[0] = rng.uniform(-np.radians(60), np.radians(60))
        for k in range(1, num_frames):
            turn = steps[k - 1] * (1 if rng.random() < 0.5 else -1)
            nxt = azimuth[k - 1] + turn
            azimuth[k] = nxt if abs(nxt) <= np.radians(60) else azimuth[k - 1] - turn
        aims = np.stack(
            [rng.uniform(-1.5, 1.5, num_frames), np.full(num_frames, 4.0), rng.uniform(1.5, 3.5, num_frames)], 1
        )
        y = rng.uniform(-3.4, -2.6, num_frames)
        centers = np.stack([aims[:, 0] - (4.0 - y) * np.tan(azimuth), y, rng.uniform(1.5, 1.9, num_frames)], 1)
        return np.stack([look_at_cam_from_world(c, a) for c, a in zip(centers, aims)])
    raise ValueError(f"no wide path for layout {layout}")
