"""Run nerfstudio's own data parsers on an ffrecon output folder and print what they give, as JSON.

Run in a subprocess by tests/formats/test_desktop_clients.py, with nerfstudio on PYTHONPATH (``make clients``
installs it in clients/python), so that nerfstudio's imports never reach the test process. Usage:
``python nerfstudio_probe.py OUT``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path


def _outputs(config) -> dict:
    """What one data parser gives for all frames: cameras (camera-to-world, OpenGL), intrinsics, distortion,
    the points, and the transform and scale it applied (``dataparser_transform``, ``dataparser_scale``)."""
    out = config.setup().get_dataparser_outputs(split="train")
    cams = out.cameras
    points = out.metadata.get("points3D_xyz")
    return {
        "files": [Path(f).name for f in out.image_filenames],
        "camera_to_worlds": cams.camera_to_worlds.double().tolist(),
        "fx": cams.fx.double().flatten().tolist(),
        "fy": cams.fy.double().flatten().tolist(),
        "cx": cams.cx.double().flatten().tolist(),
        "cy": cams.cy.double().flatten().tolist(),
        "distortion": cams.distortion_params.double().tolist() if cams.distortion_params is not None else None,
        "camera_type": [int(t) for t in cams.camera_type.flatten().tolist()],
        "transform": out.dataparser_transform.double().tolist(),
        "scale": float(out.dataparser_scale),
        "points": None if points is None else points.double().tolist(),
    }


def main(folder: Path) -> None:
    import nerfstudio
    from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParserConfig
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    result = {
        "version": getattr(nerfstudio, "__version__", ""),
        "nerfstudio": _outputs(  # splatfacto loads the points: so does this
            NerfstudioDataParserConfig(data=folder, eval_mode="all", downscale_factor=1, load_3D_points=True)
        ),
        "colmap": _outputs(ColmapDataParserConfig(data=folder, eval_mode="all", downscale_factor=1)),
    }
    print(json.dumps(result))


if __name__ == "__main__":
    main(Path(sys.argv[1]))
