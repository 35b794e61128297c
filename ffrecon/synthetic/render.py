"""Ray casting of the synthetic room in numpy: geometry, surfaces and textures, nearest hit.

The world is z-up. The scene is the inside of an axis-aligned room plus boxes turned about z and one
sphere. Every planar face is a :class:`Quad` with its own texture, addressed in world units from a
corner, so a surface point has the same colour from every view (textures and shading are
view-independent, which is what SfM and splatting assume).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ffrecon.geometry.projection import pixel_centers

_LIGHT_DIR = np.array([0.3, 0.5, 1.0]) / np.linalg.norm([0.3, 0.5, 1.0])


def lambert(normal: np.ndarray) -> np.ndarray:
    """View-independent shading factor in [0.72, 1] for ``[..., 3]`` unit normals."""
    return 0.72 + 0.28 * np.clip(normal @ _LIGHT_DIR, 0.0, 1.0)


@dataclass(frozen=True)
class Quad:
    """A textured rectangle: points ``origin + a * u_dir + b * v_dir``, ``a in [0, size_u]``, ``b in [0, size_v]``."""

    origin: np.ndarray  # [3] world
    u_dir: np.ndarray  # [3] unit
    v_dir: np.ndarray  # [3] unit
    size_u: float
    size_v: float
    normal: np.ndarray  # [3] unit, pointing to the side the cameras see


@dataclass(frozen=True)
class Box:
    """Box turned by ``yaw_rad`` about the world z axis."""

    center: np.ndarray  # [3] world
    half_size: np.ndarray  # [3], along the box's own axes
    yaw_rad: float

    @property
    def world_from_box(self) -> np.ndarray:
        """``[3, 3]`` rotation taking box-axis vectors to world vectors."""
        c, s = np.cos(self.yaw_rad), np.sin(self.yaw_rad)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class Sphere:
    center: np.ndarray  # [3] world
    radius: float


@dataclass(frozen=True)
class Geometry:
    """The room ``[room_lo, room_hi]`` seen from inside, boxes and spheres; surfaces are numbered
    room faces (6), then 6 faces per box, then one per sphere. Face ``2 * axis + side`` of the room or
    of a box lies at the low (side 0) or high (side 1) bound along that axis."""

    room_lo: np.ndarray  # [3]
    room_hi: np.ndarray  # [3]
    boxes: tuple[Box, ...]
    spheres: tuple[Sphere, ...]
    quads: tuple[Quad, ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        quads = [_face_quad(self.room_lo, self.room_hi, np.eye(3), np.zeros(3), f, inward=True) for f in range(6)]
        for box in self.boxes:
            rot = box.world_from_box
            quads += [_face_quad(-box.half_size, box.half_size, rot, box.center, f, inward=False) for f in range(6)]
        object.__setattr__(self, "quads", tuple(quads))

    @property
    def num_surfaces(self) -> int:
        return len(self.quads) + len(self.spheres)


def _face_quad(
    lo: np.ndarray, hi: np.ndarray, world_from_local: np.ndarray, offset: np.ndarray, face: int, *, inward: bool
) -> Quad:
    """Face ``2 * axis + side`` of the box ``[lo, hi]`` (local frame) as a world-frame :class:`Quad`."""
    axis, side = divmod(face, 2)
    a, b = [k for k in range(3) if k != axis]
    corner = lo.astype(np.float64).copy()
    corner[axis] = hi[axis] if side else lo[axis]
    normal = np.zeros(3)
    normal[axis] = 1.0 if side else -1.0
    if inward:
        normal = -normal
    return Quad(
        origin=world_from_local @ corner + offset,
        u_dir=world_from_local[:, a].copy(),
        v_dir=world_from_local[:, b].copy(),
        size_u=float(hi[a] - lo[a]),
        size_v=float(hi[b] - lo[b]),
        normal=world_from_local @ normal,
    )


def intersect(geometry: Geometry, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit of rays ``origin + t * dirs`` (t > 0) with the scene.

    Args:
        origin: ``[3]`` world, inside the room.
        dirs: ``[M, 3]`` world directions (any length; ``t`` is in units of their length).
    Returns:
        ``(t [M] float64, surface [M] int32)``; every ray hits (the room is closed).
    """
    # Work on contiguous per-axis columns: numpy reduces over a length-3 axis slowly.
    d = [np.ascontiguousarray(dirs[:, k], dtype=np.float64) for k in range(3)]
    with np.errstate(divide="ignore", invalid="ignore"):
        # Room from inside: the exit distance along each axis, the nearest axis wins.
        t_axis = [(np.where(d[k] > 0, geometry.room_hi[k], geometry.room_lo[k]) - origin[k]) / d[k] for k in range(3)]
    t_best = np.minimum(np.minimum(t_axis[0], t_axis[1]), t_axis[2])
    surface = np.where(t_axis[0] == t_best, 0, np.where(t_axis[1] == t_best, 2, 4)).astype(np.int32)
    surface += np.where(surface == 0, d[0] > 0, np.where(surface == 2, d[1] > 0, d[2] > 0))
    dd = d[0] ** 2 + d[1] ** 2 + d[2] ** 2
    for b, box in enumerate(geometry.boxes):
        idx = _near_rays(origin, d, dd, box.center, float(np.linalg.norm(box.half_size)))
        rot = box.world_from_box
        o_local = rot.T @ (origin - box.center)
        t_min, t_max, high_side = [], [], []
        for k in range(3):  # slabs along the box's own axes
            d_local = rot[0, k] * d[0][idx] + rot[1, k] * d[1][idx] + rot[2, k] * d[2][idx]
            with np.errstate(divide="ignore", invalid="ignore"):
                t1 = (-box.half_size[k] - o_local[k]) / d_local
                t2 = (box.half_size[k] - o_local[k]) / d_local
            t_min.append(np.minimum(t1, t2))
            t_max.append(np.maximum(t1, t2))
            high_side.append(d_local < 0)  # running towards -axis, the ray enters through the high side
        t_near = np.maximum(np.maximum(t_min[0], t_min[1]), t_min[2])
        t_far = np.minimum(np.minimum(t_max[0], t_max[1]), t_max[2])
        axis = np.where(t_min[0] == t_near, 0, np.where(t_min[1] == t_near, 1, 2))
        side = np.where(axis == 0, high_side[0], np.where(axis == 1, high_side[1], high_side[2]))
        hit = (t_near <= t_far) & (t_near > 1e-9) & (t_near < t_best[idx])
        t_best[idx[hit]] = t_near[hit]
        surface[idx[hit]] = 6 + 6 * b + 2 * axis[hit] + side[hit]
    for s, sphere in enumerate(geometry.spheres):
        idx = _near_rays(origin, d, dd, sphere.center, sphere.radius)
        oc = origin - sphere.center
        half_b = d[0][idx] * oc[0] + d[1][idx] * oc[1] + d[2][idx] * oc[2]
        disc = half_b**2 - dd[idx] * (oc @ oc - sphere.radius**2)
        t = (-half_b - np.sqrt(np.maximum(disc, 0.0))) / dd[idx]
        hit = (disc > 0) & (t > 1e-9) & (t < t_best[idx])
        t_best[idx[hit]] = t[hit]
        surface[idx[hit]] = len(geometry.quads) + s
    return t_best, surface


def _near_rays(
    origin: np.ndarray, d: list[np.ndarray], dd: np.ndarray, center: np.ndarray, radius: float
) -> np.ndarray:
    """Indices of rays (direction columns ``d``) passing within ``radius`` (plus a margin) of ``center``,
    ahead of the origin."""
    oc = center - origin
    along = d[0] * oc[0] + d[1] * oc[1] + d[2] * oc[2]
    dist_sq = oc @ oc - along**2 / dd
    return np.flatnonzero((dist_sq < (radius * 1.01 + 1e-6) ** 2) & ((along > 0) | (oc @ oc < radius**2)))


def _bilinear(texture: np.ndarray, x: np.ndarray, y: np.ndarray, *, wrap: bool) -> np.ndarray:
    """Sample ``[h, w, 3]`` at continuous texel coordinates (texel centres at k + 0.5)."""
    h, w = texture.shape[:2]
    x, y = x - 0.5, y - 0.5
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = (x - x0)[:, None].astype(np.float32), (y - y0)[:, None].astype(np.float32)
    if wrap:
        xs, ys = (x0 % w, (x0 + 1) % w), (y0 % h, (y0 + 1) % h)
    else:
        xs = (np.clip(x0, 0, w - 1), np.clip(x0 + 1, 0, w - 1))
        ys = (np.clip(y0, 0, h - 1), np.clip(y0 + 1, 0, h - 1))
    top = texture[ys[0], xs[0]] * (1 - fx) + texture[ys[0], xs[1]] * fx
    bottom = texture[ys[1], xs[0]] * (1 - fx) + texture[ys[1], xs[1]] * fx
    return top * (1 - fy) + bottom * fy


def shade(
    geometry: Geometry,
    textures: tuple[np.ndarray, ...],
    points: np.ndarray,
    surface: np.ndarray,
    *,
    texels_per_unit: tuple[float, ...],
    wrap: bool,
    contrast: float = 1.0,
) -> np.ndarray:
    """Colour ``[M, 3]`` float32 of surface points ``[M, 3]`` (world) on surfaces ``[M]``.

    ``textures[k]`` (``[h, w, 3]`` float32) covers surface k at ``texels_per_unit[k]`` texels per world unit.

    ``contrast`` scales the texture about its mean (0 gives each surface a flat colour).
    """
    out = np.empty((len(points), 3), np.float32)
    order = np.argsort(surface, kind="stable")
    surfaces, starts = np.unique(surface[order], return_index=True)
    for k, idx in zip(surfaces, np.split(order, starts[1:])):
        p = points[idx]
        if k < len(geometry.quads):
            quad = geometry.quads[k]
            rel = p - quad.origin
            u, v = rel @ quad.u_dir, rel @ quad.v_dir
            normal_shade = np.float32(lambert(quad.normal))
        else:
            sphere = geometry.spheres[k - len(geometry.quads)]
            n = (p - sphere.center) / sphere.radius
            u = sphere.radius * (np.arctan2(n[:, 1], n[:, 0]) + np.pi)
            v = sphere.radius * np.arccos(np.clip(n[:, 2], -1.0, 1.0))
            normal_shade = lambert(n).astype(np.float32)[:, None]
        tex = textures[k]
        colour = _bilinear(tex, u * texels_per_unit[k], v * texels_per_unit[k], wrap=wrap)
        if contrast != 1.0:
            mean = tex.reshape(-1, 3).mean(0)
            colour = mean + np.float32(contrast) * (colour - mean)
        out[idx] = colour * normal_shade
    return out


def camera_rays(
    cam_from_world: np.ndarray,
    K: np.ndarray,
    height: int,
    width: int,
    offsets: np.ndarray,
    *,
    fisheye: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """World-frame ray directions through sub-pixel positions, scaled so that ``t`` is z-depth.

    Args:
        cam_from_world: ``[3, 4]`` OpenCV pose.
        K: ``[3, 3]``, COLMAP pixel convention.
        offsets: ``[P, 2]`` (dx, dy) added to each pixel centre.
        fisheye: an equidistant fisheye (COLMAP's and OpenCV's fisheye model with k1..k4 = 0): a pixel at
            normalised radius r sees the ray at angle r from the optical axis (a pinhole: atan(r)).
    Returns:
        ``(origin [3], dirs [P, H, W, 3])``.
    """
    rot = cam_from_world[:, :3]
    origin = -rot.T @ cam_from_world[:, 3]
    uv = pixel_centers(height, width)[None] + offsets[:, None, None, :]
    x, y = (uv[..., 0] - K[0, 2]) / K[0, 0], (uv[..., 1] - K[1, 2]) / K[1, 1]
    if fisheye:  # angle r from the axis: the pinhole direction at radius tan(r), kept below 90 degrees
        r = np.hypot(x, y)
        stretch = np.tan(np.minimum(r, np.radians(89.0))) / np.maximum(r, 1e-12)
        x, y = x * np.where(r > 1e-12, stretch, 1.0), y * np.where(r > 1e-12, stretch, 1.0)
    d_cam = np.stack([x, y, np.ones(uv.shape[:-1])], -1)
    return origin, d_cam @ rot  # R^T d, row-vector form


def cast_depth(geometry: Geometry, cam_from_world: np.ndarray, K: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Exact z-depth ``[M]`` seen through arbitrary pixel positions ``uv [M, 2]`` (COLMAP convention)."""
    rot = cam_from_world[:, :3]
    origin = -rot.T @ cam_from_world[:, 3]
    d_cam = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(uv))], -1)
    return intersect(geometry, origin, d_cam @ rot)[0]
