"""Rotations, rigid and similarity transforms, projection, alignment and pose metrics.

All functions here are pure and work on plain numpy arrays, so they can be tested on exact inputs.
Poses are OpenCV ``cam_from_world`` as ``[..., 3, 4]`` arrays ``[R | t]`` unless the name says otherwise.
"""
