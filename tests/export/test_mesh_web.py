"""mesh.glb in three.js (the pinned clients/node_modules/three, GLTFLoader) in headless Chromium: the vertices
and triangles trimesh and open3d read. Skipped, with the reason, without node, the npm clients or Chromium."""

from __future__ import annotations

import http.server
import json
import subprocess
import threading
from pathlib import Path
from urllib.parse import parse_qs, urlparse

import numpy as np
import open3d as o3d

from ffrecon.export.mesh import DepthMaps, MeshResult, write_mesh
from ffrecon.formats.mesh import MeshOptions
from ffrecon.formats.pointcloud import FuseOptions
from ffrecon.geometry.poses import camera_centers
from ffrecon.synthetic import SceneOptions, make_scene
from ffrecon.types import ModelFamily, ModelInfo, Prediction

CLIENTS = Path(__file__).resolve().parents[2] / "clients"
PAGE = """<!doctype html><html><body style="margin:0"><canvas id="c" width="320" height="240"></canvas>
<script type="importmap">{"imports": {"three": "/three/build/three.module.js", "three/addons/": "/three/examples/jsm/"}}
</script>
<script type="module">
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
const gltf = await new GLTFLoader().loadAsync("/mesh.glb");
let vertices = 0, triangles = 0, colours = 0;
gltf.scene.traverse((o) => {
  if (!o.isMesh) return;
  const g = o.geometry;
  vertices += g.attributes.position.count;
  triangles += (g.index ? g.index.count : g.attributes.position.count) / 3;
  colours += g.attributes.color ? g.attributes.color.count : 0;
});
const renderer = new THREE.WebGLRenderer({ canvas: document.getElementById("c") });
const scene = new THREE.Scene();
scene.add(gltf.scene, new THREE.AmbientLight(0xffffff, 2));
const box = new THREE.Box3().setFromObject(gltf.scene);
const camera = new THREE.PerspectiveCamera(60, 4 / 3, 0.01, 100);
const size = box.getSize(new THREE.Vector3()).length();
camera.position.copy(box.getCenter(new THREE.Vector3()).add(new THREE.Vector3(0, 0, size)));
renderer.render(scene, camera);
await fetch(`/result?vertices=${vertices}&triangles=${triangles}&colours=${colours}`);
</script></body></html>"""


def _server(folder: Path, three: Path, results: list[dict]) -> http.server.ThreadingHTTPServer:
    """127.0.0.1 on a free port: the page, mesh.glb, three.js from ``three``, and /result (recorded)."""

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802 (http.server's name)
            url = urlparse(self.path)
            if url.path == "/result":
                results.append({k: int(float(v[0])) for k, v in parse_qs(url.query).items()})
                body, kind = b"ok", "text/plain"
            elif url.path == "/favicon.ico":  # asked for by every page; not the mesh's concern
                body, kind = b"", "image/x-icon"
            else:
                root, rel = (
                    (three, url.path[len("/three/") :]) if url.path.startswith("/three/") else (folder, url.path[1:])
                )
                file = (root / (rel or "index.html")).resolve()
                if not file.is_file() or root.resolve() not in file.parents:
                    self.send_error(404)
                    return
                body = file.read_bytes()
                kind = {".html": "text/html", ".js": "text/javascript"}.get(file.suffix, "application/octet-stream")
            self.send_response(200)
            self.send_header("Content-Type", kind)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


def test_three_js_reads_the_glb_with_the_ply_vertices(tmp_path, chromium, node_clients):
    scene = make_scene(SceneOptions(num_frames=4, width=64, height=48))
    conf = tuple(np.full_like(d, 5.0) for d in scene.depth)
    cams = (scene.camera,) * len(scene)
    pred = Prediction(
        scene.names, scene.cam_from_world, cams, tuple(scene.depth), conf, ModelInfo("t", ModelFamily.MULTIVIEW)
    )
    depth = DepthMaps(pred, list(scene.images), FuseOptions())
    mesh = write_mesh(tmp_path, MeshOptions(), (np.zeros((0, 3)),) * 2, camera_centers(pred.cam_from_world), depth)
    assert isinstance(mesh, MeshResult), mesh
    (tmp_path / "index.html").write_text(PAGE)
    results: list[dict] = []
    server = _server(tmp_path, node_clients / "three", results)
    try:
        url = f"http://127.0.0.1:{server.server_address[1]}/index.html"
        done = subprocess.run(
            ["node", str(CLIENTS / "screenshot_url.mjs"), url, str(tmp_path / "shot.png"), "320x240", "30000", "500"],
            capture_output=True,
            text=True,
            timeout=90,
            env={"CHROMIUM": str(chromium), "PATH": "/usr/bin:/bin"},
        )
    finally:
        server.shutdown()
    report = json.loads(done.stdout.strip().splitlines()[-1]) if done.stdout.strip() else {}
    assert done.returncode == 0 and results, f"{done.stderr}\n{report}"
    ply = o3d.io.read_triangle_mesh(str(mesh.ply))
    assert results[0] == {
        "vertices": len(ply.vertices),
        "triangles": len(ply.triangles),
        "colours": len(ply.vertices),
    }, report
    assert not report.get("console_errors"), report
