"""The viser server that shows a :class:`~ffrecon.view.scene.ViewScene` in the browser.

Each layer (an estimate's cameras, the points, the splat) hangs under its own scene node, so one
checkbox shows or hides it. Clicking a frustum shows its photo, its status and its pose errors.
"""

from __future__ import annotations

import contextlib
import errno
import io
import logging
import socket
from dataclasses import dataclass

import numpy as np

from ffrecon.errors import FFReconError, ResourceError
from ffrecon.view.access import AccessPolicy, Gate, guarded_serve, new_token
from ffrecon.view.panel import EditPanel
from ffrecon.view.scene import FLAG_COLOR, CameraLayer, CameraSpec, Estimate, ViewScene

logger = logging.getLogger("ffrecon.view")

THUMBNAIL_PX = 128  # long side of the photo drawn on a final-layer frustum
PANEL_PX = 480  # long side of the photo shown in the panel after a click


class PortInUse(FFReconError):
    """The viewer's port is taken by another program."""


@dataclass
class Viewer:
    """A running viewer: ``url`` to open (it carries the access token), ``select()`` does what clicking a
    camera does, ``stop()`` ends it."""

    server: object  # viser.ViserServer
    url: str
    scene: ViewScene
    details: object = None  # the "Selected camera" markdown handle
    photo: object = None  # its image handle
    edit: object = None  # the crop box and camera path tools (ffrecon.view.panel.EditPanel)

    def select(self, estimate: Estimate, name: str) -> None:
        """Show ``name``'s photo, status and pose errors in the panel, as a click on its frustum does."""
        layer = self.scene.layer(estimate)
        cam = next((c for c in layer.cameras if c.name == name), None) if layer is not None else None
        if cam is None:
            raise KeyError(f"no {estimate.label} camera named {name}")
        self._show(layer, cam)

    def _show(self, layer: CameraLayer, cam: CameraSpec) -> None:
        self.details.content = _camera_markdown(self.scene, layer, cam)
        info = self.scene.images.get(cam.name)
        image = _photo(info.path, PANEL_PX) if info is not None else None
        if image is not None:
            self.photo.image = image
        self.photo.visible = image is not None

    def stop(self, timeout_s: float = 5.0) -> bool:
        """Stop the server; False when it had not stopped after ``timeout_s`` (a connection that does not close:
        the caller then leaves without it rather than hang on Ctrl-C)."""
        import threading

        def stop() -> None:
            with contextlib.redirect_stdout(io.StringIO()):  # viser prints "Server stopped" unconditionally
                self.server.stop()

        stopper = threading.Thread(target=stop, name="ffrecon-viewer-stop", daemon=True)
        stopper.start()
        stopper.join(timeout_s)
        return not stopper.is_alive()


def _check_port_free(host: str, port: int) -> None:
    """Raise :class:`PortInUse` when ``host:port`` is taken (viser would silently move to the next port)."""
    if port == 0:
        return
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server binds
        try:
            probe.bind((host, port))
        except OSError as err:
            taken = err.errno == errno.EADDRINUSE
            raise PortInUse(
                f"cannot listen on {host}:{port}: {'the port is in use' if taken else err.strerror}",
                f"pass another port (ffrecon view OUT --port {port + 1}) or stop the program using it"
                if taken
                else "pass a host this machine has (--host 127.0.0.1)",
            ) from err


def _photo(path, long_side: int) -> np.ndarray | None:
    from PIL import Image

    if path is None:
        return None
    try:
        with Image.open(path) as im:
            im = im.convert("RGB")
            im.thumbnail((long_side, long_side))
            return np.asarray(im)
    except OSError:
        logger.warning("could not read %s; its frustum is drawn without it", path)
        return None


def _wxyz(rot: np.ndarray) -> np.ndarray:
    from ffrecon.geometry.rotations import matrix_to_quat_xyzw

    x, y, z, w = matrix_to_quat_xyzw(rot)
    return np.array([w, x, y, z])


def _frustum_scale(scene: ViewScene) -> float:
    centers = scene.centers()
    if len(centers) < 2:
        return 0.1
    gaps = np.linalg.norm(centers[:, None] - centers[None], axis=-1) + np.eye(len(centers)) * 1e9
    nearest = np.median(gaps.min(axis=1))
    extent = float(np.linalg.norm(np.ptp(centers, axis=0)))
    return float(np.clip(0.7 * nearest if nearest < 1e8 else 0.05 * extent, 0.02 * extent, 0.1 * extent) or 0.1)


def _legend_html(scene: ViewScene) -> str:
    def swatch(color, text):
        r, g, b = color
        box = f"display:inline-block;width:12px;height:12px;background:rgb({r},{g},{b})"
        return f'<div><span style="{box}"></span> {text}</div>'

    rows = [swatch(layer.color, f"{layer.estimate.label} cameras ({len(layer.cameras)})") for layer in scene.layers]
    flagged = scene.flagged
    rows.append(swatch(FLAG_COLOR, f"flagged by the cross-check ({len(flagged)}), drawn thick"))
    return '<div style="font-size:0.85em">' + "".join(rows) + "</div>"


def _status_markdown(scene: ViewScene) -> str:
    lines = []
    if scene.points is not None:
        p = scene.points
        lines.append(f"points: {len(p.xyz):,} of {p.total:,} shown")
    if scene.splat is not None:
        s = scene.splat
        lines.append(f"splat: {len(s.centers):,} of {s.total:,} Gaussians shown (most opaque first)")
    for layer in scene.layers:
        if layer.estimate is not Estimate.FINAL and layer.alignment_rms:
            lines.append(f"{layer.estimate.label}: Sim(3)-aligned to the final cameras, RMS {layer.alignment_rms:.3g}")
    lines += [f"not shown: {what} ({why})" for what, why in scene.missing]
    lines += list(scene.notes)
    if scene.flagged:
        lines.append("flagged: " + ", ".join(scene.flagged))
    return "\n".join(f"- {line}" for line in lines)


def _camera_markdown(scene: ViewScene, layer: CameraLayer, cam: CameraSpec) -> str:
    info = scene.images.get(cam.name)
    lines = [f"**{cam.name}** ({layer.estimate.label} camera)"]
    if info is not None:
        if info.status:
            lines.append(f"- status: {info.status} ({info.why})")
        lines += [f"- **flagged**: {flag}" for flag in info.flags]
        for key, err in info.errors.items():
            if err.get("rotation_deg") is not None:
                lines.append(
                    f"- {key.replace('_', ' ')}: rotation {err['rotation_deg']:.2f} deg, "
                    f"centre {err.get('center_error', float('nan')):.3g}"
                )
    return "\n".join(lines)


def _add_cameras(server, scene: ViewScene, layer: CameraLayer, scale: float, on_select):
    """The layer's frustums under one frame node (returned: hiding it hides them all)."""
    root = f"/{layer.estimate.name.lower()}"
    frame = server.scene.add_frame(root, show_axes=False)
    thickness = 0.05 * scale
    for cam in layer.cameras:
        info = scene.images.get(cam.name)
        image = _photo(info.path, THUMBNAIL_PX) if (layer.estimate is Estimate.FINAL and info) else None
        handle = server.scene.add_camera_frustum(
            f"{root}/{cam.name.replace('/', '_')}",
            fov=cam.fov_y,
            aspect=cam.aspect,
            scale=scale,
            thickness=thickness * (3.0 if cam.flagged else 1.0),
            color=FLAG_COLOR if cam.flagged else layer.color,
            image=image,
            wxyz=_wxyz(cam.world_from_cam[:, :3]),
            position=cam.world_from_cam[:, 3],
            cast_shadow=False,
            receive_shadow=False,
        )
        handle.on_click(lambda _event, layer=layer, cam=cam: on_select(layer, cam))
    return frame


def _frame_view(server, scene: ViewScene) -> None:
    up = scene.up()
    server.scene.set_up_direction(tuple(float(v) for v in up))
    centers = scene.centers()
    if len(centers) == 0 and scene.points is not None:
        centers = scene.points.xyz.astype(np.float64)
    if len(centers) == 0:
        return
    look_at = centers.mean(axis=0)
    radius = max(float(np.linalg.norm(centers - look_at, axis=1).max()), 1e-3)
    # From above and outside the ring of cameras, looking down at its centre.
    mean_forward = np.mean([c.world_from_cam[:, 2] for layer in scene.layers for c in layer.cameras] or [[1, 0, 0]], 0)
    side = -mean_forward - up * float(np.dot(-mean_forward, up))
    side = side / np.linalg.norm(side) if np.linalg.norm(side) > 1e-6 else np.cross(up, [1.0, 0.0, 0.0])
    position = look_at + radius * (1.0 * side + 2.2 * up)
    server.initial_camera.position = tuple(float(v) for v in position)
    server.initial_camera.look_at = tuple(float(v) for v in look_at)
    server.initial_camera.up = tuple(float(v) for v in up)


def start_viewer(scene: ViewScene, *, host: str = "127.0.0.1", port: int = 8080) -> Viewer:
    """Serve ``scene`` on ``http://host:port`` (in a background thread) and return the running viewer.

    Only the viewer's own page, opened from ``viewer.url`` (which carries a fresh ``?token=``), may read
    the scene: :mod:`ffrecon.view.access` checks Host, Origin and the token on every request.

    Raises:
        PortInUse: the port is taken (viser itself would move to another one without saying).
        ResourceError: the installed viser starts its server in a way the access checks cannot guard.
    """
    _check_port_free(host, port)
    import viser

    gate = Gate()
    with guarded_serve(gate), contextlib.redirect_stdout(io.StringIO()):  # its banner; the CLI prints the URL
        server = viser.ViserServer(host=host, port=port, label="ffrecon", verbose=False)
    token = new_token()
    gate.open(AccessPolicy(host=host, port=server.get_port(), token=token))
    address = f"http://{'[' + host + ']' if ':' in host else host}:{server.get_port()}"
    viewer = Viewer(server, f"{address}/?token={token}", scene)
    if not gate.installed:  # this viser starts its server another way: refuse to serve the scene unguarded
        viewer.stop()
        raise ResourceError(
            f"viser {viser.__version__} starts its web server in a way ffrecon cannot guard "
            "(no token or origin checks), so the viewer is not started",
            "install a viser that ffrecon supports: pip install 'viser==1.1.1'",
        )
    if port and server.get_port() != port:  # taken between the check and the bind
        viewer.stop()
        _check_port_free(host, port)
        raise PortInUse(f"port {port} on {host} is in use", f"pass another port (--port {port + 1})")
    _populate(viewer)
    return viewer


def _populate(viewer: Viewer) -> None:
    server, scene = viewer.server, viewer.scene
    gui = server.gui
    gui.configure_theme(control_width="large", show_share_button=False)
    gui.add_markdown(f"**ffrecon** · `{scene.out_dir}`")
    with gui.add_folder("Layers"):
        gui.add_html(_legend_html(scene))
        toggles = gui.add_folder("show")
        gui.add_markdown(_status_markdown(scene))
    with gui.add_folder("Selected camera"):
        viewer.details = gui.add_markdown("click a camera to see its photo and pose errors")
        viewer.photo = gui.add_image(np.full((4, 4, 3), 255, np.uint8), label="photo", visible=False)

    scale = _frustum_scale(scene)
    nodes = {
        f"{layer.estimate.label} cameras": _add_cameras(server, scene, layer, scale, viewer._show)
        for layer in scene.layers
    }
    if scene.points is not None:
        nodes["points"] = server.scene.add_point_cloud(
            "/points", scene.points.xyz, scene.points.rgb, point_size=0.15 * scale, point_shape="rounded"
        )
    if scene.splat is not None:
        s = scene.splat
        nodes["splat"] = server.scene.add_gaussian_splats("/splat", s.centers, s.covariances, s.rgbs, s.opacities)
    with toggles:
        for label, handle in nodes.items():
            box = gui.add_checkbox(label, initial_value=True)
            box.on_update(lambda event, handle=handle: setattr(handle, "visible", event.target.value))
    viewer.edit = EditPanel(server, scene, scale)
    viewer.edit.build()
    _frame_view(server, scene)
