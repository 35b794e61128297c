"""Render an output folder's splat in Spark (three.js, headless Chromium) and in ffrecon from the same
training camera, and print the PSNR between the two pictures: the check that a web viewer shows the
scene ffrecon trained (issue 11's acceptance on the demo: at least 25 dB).

    python tools/spark_compare.py demo_out [--views 3]

Needs `make clients` (Debian's chromium and clients/node_modules). Writes the pictures next to a
job file in a temporary folder and prints where.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from ffrecon.formats.splat_ply import read_splat_ply
from ffrecon.splat.optimize import OptimizeOptions
from ffrecon.splat.render import render_view
from ffrecon.types import PinholeCamera

CLIENTS = Path(__file__).resolve().parents[1] / "clients"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path, help="an ffrecon output folder with splat.ply (and splat.spz)")
    parser.add_argument("--views", type=int, default=3, help="training cameras to compare from")
    args = parser.parse_args()
    report = json.loads((args.out / "report.json").read_text())
    heldout = set(report["splat"]["heldout_views"])
    rec = pycolmap.Reconstruction(str(args.out / "sparse" / "0"))
    images = [im for _, im in sorted(rec.images.items()) if im.name not in heldout]
    picks = [images[k] for k in np.linspace(0, len(images) - 1, args.views).round().astype(int)]
    o = OptimizeOptions.brief()  # the background and rasteriser settings the splat stage used
    g = read_splat_ply(args.out / "splat.ply")
    work = Path(tempfile.mkdtemp(prefix="spark-compare-"))
    files = {k: args.out / f"splat.{k}" for k in ("ply", "spz") if (args.out / f"splat.{k}").is_file()}
    for image in picks:
        cam = rec.cameras[image.camera_id]
        camera = PinholeCamera(
            cam.width, cam.height, cam.focal_length_x, cam.focal_length_y, cam.principal_point_x, cam.principal_point_y
        )
        cam_from_world = image.cam_from_world().matrix()
        ours = render_view(g, cam_from_world, camera, background=o.background, raster=o.raster).numpy()
        stem = Path(image.name).stem
        cv2.imwrite(str(work / f"{stem}_ffrecon.png"), cv2.cvtColor(np.uint8(ours * 255 + 0.5), cv2.COLOR_RGB2BGR))
        job = {
            "chromium": "/usr/bin/chromium",
            "width": camera.width,
            "height": camera.height,
            **{k: getattr(camera, k) for k in ("fx", "fy", "cx", "cy")},
            "cam_from_world": np.asarray(cam_from_world).tolist(),
            "background": list(o.background),
            "eps2d": o.raster.eps2d,
            "renders": [{"splat": str(p), "out": str(work / f"{stem}_spark_{k}.png")} for k, p in files.items()],
        }
        (work / "job.json").write_text(json.dumps(job))
        subprocess.run(["node", str(CLIENTS / "spark_render.mjs"), str(work / "job.json")], check=True, timeout=600)
        for k in files:
            bgr = cv2.imread(str(work / f"{stem}_spark_{k}.png"))
            theirs = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).astype(np.float64) / 255.0
            psnr = 10 * np.log10(1.0 / max(float(np.mean((theirs - ours) ** 2)), 1e-12))
            print(f"{image.name} splat.{k}: Spark vs ffrecon {psnr:.1f} dB ({camera.width}x{camera.height})")
    print(f"pictures: {work}")


if __name__ == "__main__":
    main()
