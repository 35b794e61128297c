"""ffrecon: photos or video in, a verified 3D reconstruction out.

The pipeline is Capture -> Pose (feed-forward, COLMAP) -> Refine -> Splat -> Export/Report;
each stage lives in the sub-package of that name and :func:`ffrecon.pipeline.run` chains them.
"""

import logging

__version__ = "0.1.0"

logger = logging.getLogger("ffrecon")
logger.addHandler(logging.NullHandler())
