"""Synthetic textured scenes with exact ground truth (cameras, poses, depth), rendered on the CPU.

A closed room (x, y in [-3, 3], z in [0, 2.6], world z up) with textured boxes and a sphere near the
centre, seen by OpenCV pinhole cameras on an orbit, an arc, a forward walk or a few wide steps around
the objects. Rendering is numpy ray casting with 2x2 supersampling; ``depth`` is the exact z-depth
along the ray through each pixel centre (COLMAP rule: pixel ``(row v, col u)`` has its centre at
``(u + 0.5, v + 0.5)``), so ``unproject_depth(depth[i], K, cam_from_world[i])`` gives exact surface
points.

>>> scene = make_scene(SceneOptions(num_frames=2, width=32, height=24))
>>> scene.images.shape, scene.depth.dtype, scene.camera.cx
((2, 24, 32, 3), dtype('float32'), 16.0)
"""

from __future__ import annotations

import enum
import json
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from ffrecon.formats.ground_truth import read_ground_truth
from ffrecon.geometry.poses import look_at_cam_from_world
from ffrecon.geometry.projection import unproject_depth
from ffrecon.synthetic import render, textures
from ffrecon.synthetic.layouts import Layout, layout_spec, wide_path
from ffrecon.types import PinholeCamera

logger = logging.getLogger("ffrecon.synthetic")

ROOM_LO = np.array([-3.0, -3.0, 0.0])
ROOM_HI = np.array([3.0, 3.0, 2.6])
LOOK_TARGET = np.array([0.0, 0.0, 0.55])  # the middle of the objects, where orbit and arc cameras look
ORBIT_RADIUS = 1.75
CAMERA_HEIGHT = 1.35
_SUPERSAMPLE_OFFSETS = np.array([[-0.25, -0.25], [0.25, -0.25], [-0.25, 0.25], [0.25, 0.25]])
_TEXTURELESS_CONTRAST = 0.01
WIDE_STEP_DEG = (30.0, 60.0)  # the wide path's turn about the centre between consecutive views
ROOM_TEXELS_PER_UNIT = 64.0  # texture resolution of the room's walls, floor and ceiling
OBJECT_TEXELS_PER_UNIT = 128.0  # and of the boxes and the sphere, seen from closer
# Room faces (2 * axis + side) near-uniform with Texture.PLAIN_WALLS: the walls at x = 3 and y = 3, the ceiling.
PLAIN_SURFACES = (1, 3, 5)


class CameraPath(enum.Enum):
    ORBIT = "orbit"  # full circle around the centre, looking in
    ARC = "arc"  # 90 degree arc around the centre, looking in
    FORWARD = "forward"  # walk past the objects, looking ahead
    # A sparse capture around the objects, looking in: each view turns 30 to 60 degrees (drawn from the
    # seed) from the previous one about the centre, at jittered distance and height (issue 21's scenes).
    WIDE = "wide"
    # Forward-facing (LLFF-style): cameras on a small grid on one side of the objects, all looking the
    # same way (+y), towards the objects and, with SceneOptions.backdrop, a far wall beyond them.
    FACING = "facing"


class Texture(enum.Enum):
    RICH = "rich"  # distinct, multi-scale colour detail on every surface
    TEXTURELESS = "textureless"  # near-uniform surfaces
    REPEATED = "repeated"  # one tile repeated on every surface (look-alike views)
    PLAIN_WALLS = "plain_walls"  # two near-uniform walls and ceiling (PLAIN_SURFACES), the rest rich
    # Crops of real photos (SceneOptions.photo_dir) on every surface; with plain walls, the layout's plain ones.
    PHOTOS = "photos"
    PHOTOS_PLAIN_WALLS = "photos_plain_walls"


@dataclass(frozen=True, kw_only=True)
class SceneOptions:
    num_frames: int = 24
    width: int = 320
    height: int = 240
    fov_x_deg: float = 60.0
    # An equidistant fisheye (COLMAP's OPENCV_FISHEYE with k1..k4 = 0) of fov_x_deg across the width instead
    # of a pinhole: 120 deg on 320x240 is about 150 deg across the diagonal. The camera's K is the fisheye's.
    fisheye: bool = False
    path: CameraPath = CameraPath.ORBIT
    texture: Texture = Texture.RICH
    blur_sigma_px: float = 0.0  # Gaussian blur on every frame, pixels
    exposure_jitter: float = 0.0  # std of the per-frame log-gain (exposure drift)
    textureless_frames: tuple[int, ...] = ()  # frames rendered with texture contrast ~0
    seed: int = 0
    # > 0: the room's far wall (y = 3) moves out to y = 3 + backdrop, so the background (that wall and the
    # floor, ceiling and side walls leading to it) lies far beyond the cameras, as in forward-facing photos.
    backdrop: float = 0.0
    # The scene's layout (ffrecon.synthetic.layouts): the objects in a room (default), a furnished room seen
    # from inside, one object in a hall, a street facade. Layouts other than OBJECTS take the WIDE path only.
    layout: Layout = Layout.OBJECTS
    # The wide path's turn between consecutive views, degrees (low, high); None: the layout's default.
    step_deg: tuple[float, float] | None = None
    photo_dir: str = ""  # folder of photos the PHOTOS textures are cut from

    def __post_init__(self) -> None:
        if self.layout is not Layout.OBJECTS and self.path is not CameraPath.WIDE:
            raise ValueError(f"layout {self.layout.value} has only the wide path, got {self.path.value}")
        if self.texture in (Texture.PHOTOS, Texture.PHOTOS_PLAIN_WALLS) and not self.photo_dir:
            raise ValueError("photo textures need SceneOptions.photo_dir (a folder of photos)")

    def to_dict(self) -> dict:
        out = asdict(self)
        out.update(path=self.path.value, texture=self.texture.value, textureless_frames=list(self.textureless_frames))
        out.update(layout=self.layout.value, step_deg=None if self.step_deg is None else list(self.step_deg))
        return out

    @staticmethod
    def from_dict(data: dict) -> "SceneOptions":
        data = dict(data)
        data.update(
            path=CameraPath(data["path"]),
            texture=Texture(data["texture"]),
            textureless_frames=tuple(int(i) for i in data["textureless_frames"]),
            layout=Layout(data.get("layout", Layout.OBJECTS.value)),
            step_deg=None if data.get("step_deg") is None else tuple(float(v) for v in data["step_deg"]),
        )
        return SceneOptions(**data)


@dataclass(frozen=True)
class SyntheticScene:
    """Rendered frames and their exact ground truth."""

    options: SceneOptions
    names: tuple[str, ...]  # "frame_000.png", ...
    images: np.ndarray = field(repr=False)  # [N, H, W, 3] uint8 RGB
    cam_from_world: np.ndarray = field(repr=False)  # [N, 3, 4] float64, OpenCV, ground truth
    camera: PinholeCamera  # shared intrinsics, COLMAP pixel convention (cx = W / 2 exactly)
    depth: np.ndarray = field(repr=False)  # [N, H, W] float32 z-depth; every pixel hits geometry

    def __len__(self) -> int:
        return len(self.names)

    def frame_points(self, i: int) -> np.ndarray:
        """``[H, W, 3]`` float64 world points seen by frame ``i`` (its depth unprojected)."""
        return unproject_depth(self.depth[i], self.camera.K, self.cam_from_world[i])


def scene_geometry(backdrop: float = 0.0, layout: Layout = Layout.OBJECTS) -> render.Geometry:
    """The fixed room (its far wall ``backdrop`` further out), boxes and sphere (the seed changes textures
    and jitter, not the layout); another ``layout``'s own geometry (:mod:`ffrecon.synthetic.layouts`)."""
    if layout is not Layout.OBJECTS:
        return layout_spec(layout).geometry
    boxes = (
        render.Box(
            center=np.array([0.15, -0.1, 0.225]), half_size=np.array([0.45, 0.3, 0.225]), yaw_rad=np.radians(20)
        ),
        render.Box(
            center=np.array([-0.45, 0.4, 0.55]), half_size=np.array([0.17, 0.17, 0.55]), yaw_rad=np.radians(-15)
        ),
        render.Box(center=np.array([0.5, 0.5, 0.15]), half_size=np.array([0.2, 0.15, 0.15]), yaw_rad=np.radians(40)),
        render.Box(center=np.array([0.2, -0.12, 0.6]), half_size=np.array([0.15, 0.15, 0.15]), yaw_rad=np.radians(55)),
    )
    spheres = (render.Sphere(center=np.array([-0.35, -0.6, 0.22]), radius=0.22),)
    room_hi = ROOM_HI + np.array([0.0, backdrop, 0.0])
    return render.Geometry(room_lo=ROOM_LO, room_hi=room_hi, boxes=boxes, spheres=spheres)


def camera_path(
    path: CameraPath,
    num_frames: int,
    *,
    seed: int = 0,
    layout: Layout = Layout.OBJECTS,
    step_deg: tuple[float, float] | None = None,
) -> np.ndarray:
    """``[N, 3, 4]`` cam_from_world poses (OpenCV) along ``path``; ``seed`` draws the wide path's steps."""
    if layout is not Layout.OBJECTS:
        return wide_path(layout, num_frames, seed, step_deg or layout_spec(layout).step_deg)
    if path is CameraPath.WIDE:
        centers = _wide_centers(num_frames, seed, step_deg)
        return np.stack([look_at_cam_from_world(c, LOOK_TARGET) for c in centers])
    if path in (CameraPath.ORBIT, CameraPath.ARC):
        if path is CameraPath.ORBIT:
            angles = np.radians(-90.0) + 2 * np.pi * np.arange(num_frames) / num_frames
        else:
            angles = np.radians(np.linspace(-135.0, -45.0, num_frames))
        centers = np.stack(
            [ORBIT_RADIUS * np.cos(angles), ORBIT_RADIUS * np.sin(angles), np.full(num_frames, CAMERA_HEIGHT)], axis=1
        )
        return np.stack([look_at_cam_from_world(c, LOOK_TARGET) for c in centers])
    if path is CameraPath.FACING:  # a 4-wide grid, 0.2 x 0.08 apart, at y = -2.2, looking along +y
        cols = 4
        k = np.arange(num_frames)
        x = (k % cols - (cols - 1) / 2) * 0.2
        z = CAMERA_HEIGHT + ((k // cols) - (num_frames - 1) // cols / 2) * 0.08
        centers = np.stack([x, np.full(num_frames, -2.2), z], axis=1)
        return np.stack([look_at_cam_from_world(c, c + np.array([0.0, 1.0, -0.25])) for c in centers])
    # Forward: walk along +x beside the objects, heading slightly towards them, with a gentle bob.
    s = np.linspace(0.0, 1.0, num_frames)
    centers = np.stack(
        [-2.3 + 3.0 * s, np.full(num_frames, -1.45), CAMERA_HEIGHT + 0.04 * np.sin(6 * np.pi * s)], axis=1
    )
    heading = np.array([1.0, 0.28, -0.22])
    return np.stack([look_at_cam_from_world(c, c + heading) for c in centers])


def _wide_centers(num_frames: int, seed: int, step_deg: tuple[float, float] | None = None) -> np.ndarray:
    """``[N, 3]`` world camera centres of the wide path: steps of ``WIDE_STEP_DEG`` about the centre.

    The steps, distances (0.9 to 1.15 x the orbit radius) and heights (+-0.25) come from a stream of
    their own, so the textures drawn from ``seed`` stay those of the other paths.
    """
    rng = np.random.default_rng([seed, 21])
    steps = rng.uniform(*(step_deg or WIDE_STEP_DEG), size=max(num_frames - 1, 0))
    angles = np.radians(-90.0 + np.concatenate([[0.0], np.cumsum(steps)]))
    radii = ORBIT_RADIUS * rng.uniform(0.9, 1.15, num_frames)
    heights = CAMERA_HEIGHT + rng.uniform(-0.25, 0.25, num_frames)
    return np.stack([radii * np.cos(angles), radii * np.sin(angles), heights], axis=1)


def make_camera(options: SceneOptions) -> PinholeCamera:
    """Square-pixel pinhole with the principal point exactly at the image centre."""
    half = np.radians(options.fov_x_deg) / 2
    focal = options.width / 2 / (half if options.fisheye else np.tan(half))
    return PinholeCamera(
        options.width, options.height, float(focal), float(focal), options.width / 2, options.height / 2
    )


def _surface_textures(
    geometry: render.Geometry,
    texture: Texture,
    rng: np.random.Generator,
    *,
    plain_surfaces: tuple[int, ...] = PLAIN_SURFACES,
    photo_dir: str = "",
) -> tuple[tuple[np.ndarray, ...], tuple[float, ...]]:
    """One texture per surface and its texels per world unit.

    The room's surfaces get half the objects' texel density, so their detail stays a few pixels wide
    where it is seen from far away.
    """
    num_room = 6
    if texture is Texture.REPEATED:
        tile = textures.tile_texture(rng, int(OBJECT_TEXELS_PER_UNIT * 0.75))
        return tuple(tile for _ in range(geometry.num_surfaces)), (OBJECT_TEXELS_PER_UNIT,) * geometry.num_surfaces
    sizes = [(q.size_v, q.size_u) for q in geometry.quads] + [
        (np.pi * s.radius, 2 * np.pi * s.radius) for s in geometry.spheres
    ]
    densities = tuple(ROOM_TEXELS_PER_UNIT if k < num_room else OBJECT_TEXELS_PER_UNIT for k in range(len(sizes)))
    out = []
    for k, ((size_v, size_u), density) in enumerate(zip(sizes, densities)):
        h, w = max(4, int(np.ceil(size_v * density))), max(4, int(np.ceil(size_u * density)))
        plain = texture is Texture.TEXTURELESS or (
            texture in (Texture.PLAIN_WALLS, Texture.PHOTOS_PLAIN_WALLS) and k in plain_surfaces
        )
        if plain:
            out.append(textures.plain_texture(rng, h, w))
        elif texture in (Texture.PHOTOS, Texture.PHOTOS_PLAIN_WALLS):
            out.append(textures.photo_texture(rng, h, w, photo_dir))
        else:
            out.append(textures.rich_texture(rng, h, w))
    return tuple(out), densities


def make_scene(options: SceneOptions = SceneOptions()) -> SyntheticScene:
    """Render ``options.num_frames`` frames of the room with exact depth and poses."""
    if options.num_frames < 1 or options.width < 2 or options.height < 2:
        raise ValueError(f"need num_frames >= 1 and an image of at least 2x2, got {options}")
    bad = [i for i in options.textureless_frames if not 0 <= i < options.num_frames]
    if bad:
        raise ValueError(f"textureless_frames {bad} outside 0..{options.num_frames - 1}")
    start = time.perf_counter()
    rng = np.random.default_rng(options.seed)
    geometry = scene_geometry(options.backdrop, options.layout)
    plain = PLAIN_SURFACES if options.layout is Layout.OBJECTS else layout_spec(options.layout).plain_surfaces
    surface_textures, densities = _surface_textures(
        geometry, options.texture, rng, plain_surfaces=plain, photo_dir=options.photo_dir
    )
    gains = np.exp(options.exposure_jitter * rng.standard_normal(options.num_frames))
    camera = make_camera(options)
    poses = camera_path(
        options.path, options.num_frames, seed=options.seed, layout=options.layout, step_deg=options.step_deg
    )
    h, w = options.height, options.width
    images = np.empty((options.num_frames, h, w, 3), np.uint8)
    depth = np.empty((options.num_frames, h, w), np.float32)
    offsets = np.concatenate([np.zeros((1, 2)), _SUPERSAMPLE_OFFSETS])  # centre ray first: depth
    for i, cam_from_world in enumerate(poses):
        origin, dirs = render.camera_rays(cam_from_world, camera.K, h, w, offsets, fisheye=options.fisheye)
        flat = dirs.reshape(-1, 3)
        t, surface = render.intersect(geometry, origin, flat)
        depth[i] = t[: h * w].reshape(h, w)
        contrast = 1.0
        if options.texture is Texture.TEXTURELESS or i in options.textureless_frames:
            contrast = _TEXTURELESS_CONTRAST
        points = origin + t[h * w :, None] * flat[h * w :]
        colour = render.shade(
            geometry,
            surface_textures,
            points,
            surface[h * w :],
            texels_per_unit=densities,
            wrap=options.texture is Texture.REPEATED,
            contrast=contrast,
        )
        img = colour.reshape(4, h, w, 3).mean(0) * np.float32(gains[i])
        if options.blur_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), options.blur_sigma_px)
        images[i] = np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)
    logger.debug("rendered %d frames of %dx%d in %.2f s", options.num_frames, w, h, time.perf_counter() - start)
    names = tuple(f"frame_{i:03d}.png" for i in range(options.num_frames))
    return SyntheticScene(options=options, names=names, images=images, cam_from_world=poses, camera=camera, depth=depth)


def write_scene(scene: SyntheticScene, out_dir: Path) -> Path:
    """Write ``out_dir/images/<names>`` (PNG), ``ground_truth.json`` and ``depth.npz``; returns the images folder.

    ``ground_truth.json`` holds the options, the camera (COLMAP pixel convention) and per-frame
    ``cam_from_world`` (3x4, OpenCV); ``depth.npz`` holds ``depth`` ``[N, H, W]`` float32 z-depth.
    """
    out_dir = Path(out_dir)
    image_dir = out_dir / "images"
    image_dir.mkdir(parents=True, exist_ok=True)
    for name, image in zip(scene.names, scene.images):
        Image.fromarray(image).save(image_dir / name)
    cam = scene.camera
    truth = {
        "description": "ffrecon synthetic scene: exact ground truth. Poses are OpenCV cam_from_world; "
        "pixel centres follow COLMAP (top-left pixel centre at (0.5, 0.5)); world z is up.",
        "options": scene.options.to_dict(),
        "camera": {
            "model": "PINHOLE",
            "width": cam.width,
            "height": cam.height,
            "fx": cam.fx,
            "fy": cam.fy,
            "cx": cam.cx,
            "cy": cam.cy,
        },
        "frames": [{"name": n, "cam_from_world": p.tolist()} for n, p in zip(scene.names, scene.cam_from_world)],
    }
    (out_dir / "ground_truth.json").write_text(json.dumps(truth, indent=1))
    np.savez_compressed(out_dir / "depth.npz", depth=scene.depth)
    return image_dir


def load_scene(out_dir: Path) -> SyntheticScene:
    """Read a scene written by :func:`write_scene`."""
    out_dir = Path(out_dir)
    truth = read_ground_truth(out_dir)
    names = tuple(f["name"] for f in truth["frames"])
    images = np.stack([np.asarray(Image.open(out_dir / "images" / n).convert("RGB")) for n in names])
    c = truth["camera"]
    camera = PinholeCamera(
        int(c["width"]), int(c["height"]), float(c["fx"]), float(c["fy"]), float(c["cx"]), float(c["cy"])
    )
    with np.load(out_dir / "depth.npz") as data:
        depth = data["depth"].astype(np.float32)
    return SyntheticScene(
        options=SceneOptions.from_dict(truth["options"]),
        names=names,
        images=images,
        cam_from_world=np.array([f["cam_from_world"] for f in truth["frames"]], dtype=np.float64),
        camera=camera,
        depth=depth,
    )
