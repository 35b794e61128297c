"""The viewer's editing panel: a crop box a person drags and resizes over the splat and points, with a button
that writes the cropped splat, and keyframes from the browser's camera written as a camera path.

The box has a handle at each corner (``lo`` and ``hi``: drag one to resize) and one at its centre (drag it to
move the whole box), and two number fields that show and set the corners. What the buttons write is
:mod:`ffrecon.view.edit`'s.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ffrecon.errors import FFReconError
from ffrecon.view.edit import KeyframeRecorder, write_cropped_splat
from ffrecon.view.scene import Estimate, ViewScene

logger = logging.getLogger("ffrecon.view")

BOX_COLOR = (255, 0, 255)  # magenta: no camera layer's colour (scene.Estimate) nor the flag's
DEFAULT_SIZE_WH = (1280, 720)  # a recorded path's size when the folder has no final camera to take it from


def initial_box(scene: ViewScene) -> tuple[np.ndarray, np.ndarray]:
    """``(lo [3], hi [3])``: the bounds of the splat shown (else the points, else the cameras), a little wider."""
    for xyz in (scene.splat and scene.splat.centers, scene.points and scene.points.xyz, scene.centers()):
        if xyz is not None and len(xyz):
            lo, hi = np.min(xyz, axis=0).astype(np.float64), np.max(xyz, axis=0).astype(np.float64)
            pad = 0.02 * np.maximum(hi - lo, 1e-3)
            return lo - pad, hi + pad
    return -np.ones(3), np.ones(3)


def path_size(scene: ViewScene) -> tuple[int, int]:
    """A recorded path's ``(width, height)``: the first final camera's photo size."""
    layer = scene.layer(Estimate.FINAL)
    return tuple(layer.cameras[0].size_wh) if layer is not None and layer.cameras else DEFAULT_SIZE_WH


class EditPanel:
    """The crop box and keyframe tools of one viewer. ``set_box``, ``write_crop``, ``add_keyframe`` and
    ``write_path`` do what the handles and buttons do (the tests call them)."""

    def __init__(self, server, scene: ViewScene, scale: float) -> None:
        self.server, self.scene, self.scale = server, scene, scale
        self.lo, self.hi = initial_box(scene)
        self.recorder = KeyframeRecorder()
        self.out_dir = Path(scene.out_dir)

    def build(self) -> None:
        """Add the panel's folders to the GUI and the box's handles to the scene."""
        gui, scene = self.server.gui, self.server.scene
        with gui.add_folder("Crop box"):
            self.show = gui.add_checkbox("show crop box", initial_value=True)
            self.lo_field = gui.add_vector3("lo (x, y, z)", tuple(self.lo), step=1e-3)
            self.hi_field = gui.add_vector3("hi (x, y, z)", tuple(self.hi), step=1e-3)
            crop = gui.add_button("write cropped splat", hint="splat_cropped.ply/.spz and crop_box.json in OUT")
            self.crop_status = gui.add_markdown("splat.ply stays as it is; the crop goes to splat_cropped.ply")
        with gui.add_folder("Camera path", expand_by_default=False):
            add = gui.add_button("add keyframe (this view)")
            clear = gui.add_button("clear keyframes")
            self.fps = gui.add_number("fps", 30, min=1, max=120, step=1)
            self.seconds = gui.add_number("seconds", 4.0, min=0.1, max=600.0, step=0.1)
            write = gui.add_button("write camera path", hint="camera_path_recorded.json in OUT")
            self.path_status = gui.add_markdown("no keyframes yet")
        size = 0.15 * float(np.median(self.hi - self.lo))  # the handles' size, world units
        self.handles = {
            name: scene.add_transform_controls(
                f"/crop_box/{name}",
                scale=max(size, self.scale),
                disable_rotations=True,
                depth_test=False,  # drawn over the splat, so a person can always grab them
                position=tuple(self._corner(name)),
            )
            for name in ("lo", "hi", "centre")
        }
        for name, handle in self.handles.items():
            handle.on_update(lambda _event, name=name: self._dragged(name))
        self.lo_field.on_update(lambda _event: self.set_box(self.lo_field.value, self.hi))
        self.hi_field.on_update(lambda _event: self.set_box(self.lo, self.hi_field.value))
        self.show.on_update(lambda _event: self._draw())
        crop.on_click(lambda _event: self.write_crop())
        add.on_click(lambda event: event.client is not None and self.add_keyframe(event.client.camera))
        clear.on_click(lambda _event: self.clear_keyframes())
        write.on_click(lambda _event: self.write_path())
        self._draw()

    def _corner(self, name: str) -> np.ndarray:
        return {"lo": self.lo, "hi": self.hi, "centre": (self.lo + self.hi) / 2}[name]

    def _dragged(self, name: str) -> None:
        moved = np.asarray(self.handles[name].position, np.float64)
        if name == "centre":
            shift = moved - (self.lo + self.hi) / 2
            self.set_box(self.lo + shift, self.hi + shift)
        else:
            self.set_box(moved if name == "lo" else self.lo, moved if name == "hi" else self.hi)

    def set_box(self, lo, hi) -> None:
        """Set the box's corners (where a corner passes the other, the two swap on that axis)."""
        lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        self.lo, self.hi = np.minimum(lo, hi), np.maximum(lo, hi)
        self._draw()

    def _draw(self) -> None:
        visible = bool(self.show.value)
        for name, handle in self.handles.items():
            handle.position = tuple(float(v) for v in self._corner(name))
            handle.visible = visible
        self.lo_field.value = tuple(float(v) for v in self.lo)
        self.hi_field.value = tuple(float(v) for v in self.hi)
        self.box = self.server.scene.add_box(
            "/crop_box/box",
            color=BOX_COLOR,
            dimensions=tuple(float(v) for v in np.maximum(self.hi - self.lo, 1e-9)),
            wireframe=True,
            position=tuple(float(v) for v in (self.lo + self.hi) / 2),
            cast_shadow=False,
            receive_shadow=False,
            visible=visible,
        )

    def write_crop(self):
        """Write the cropped splat and the box (:func:`~ffrecon.view.edit.write_cropped_splat`); the result, or
        None when it could not (the reason in the panel and the log)."""
        try:
            done = write_cropped_splat(self.out_dir, (tuple(self.lo), tuple(self.hi)))
        except FFReconError as err:
            self.crop_status.content = f"not written: {err.problem}"
            logger.warning("crop box: %s", err.problem)
            return None
        self.crop_status.content = (
            f"wrote `{done.ply.name}` ({done.kept:,} of {done.total:,} Gaussians), `{done.spz.name}` and "
            f"`{done.box_file.name}` (`ffrecon run ... --crop-box {done.box_file}`)"
        )
        return done

    def add_keyframe(self, camera) -> int:
        """Add a viser camera (the browser's view) as a keyframe, with a frustum where it is."""
        count = self.recorder.add_viser_camera(camera.position, camera.wxyz, camera.fov)
        width, height = path_size(self.scene)
        self.server.scene.add_camera_frustum(
            f"/keyframes/{count}",
            fov=float(camera.fov),
            aspect=width / height,
            scale=self.scale,
            color=BOX_COLOR,
            wxyz=tuple(camera.wxyz),
            position=tuple(camera.position),
        )
        self.path_status.content = f"{count} keyframe{'s' if count > 1 else ''}"
        return count

    def clear_keyframes(self) -> None:
        self.recorder.clear()
        self.server.scene.remove_by_name("/keyframes")
        self.path_status.content = "no keyframes yet"

    def write_path(self) -> Path | None:
        """Write the keyframes as ``camera_path_recorded.json``; its path, or None (the reason in the panel)."""
        try:
            path = self.recorder.write(self.out_dir, path_size(self.scene), self.fps.value, self.seconds.value)
        except FFReconError as err:
            self.path_status.content = f"not written: {err.problem}"
            return None
        self.path_status.content = (
            f"wrote `{path.name}`; render it with `ffrecon render {self.out_dir} --camera-path {path} -o path.mp4`"
        )
        return path
