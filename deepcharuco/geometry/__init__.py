"""Geometry: the camera model and its files, and a board's pose from its corners (PnP).

Imports `deepcharuco.core` and `deepcharuco.boards`.
"""

from deepcharuco.geometry.camera import Camera, read_camera, write_camera
from deepcharuco.geometry.pose import Pose, estimate_pose, project_corners

__all__ = ["Camera", "read_camera", "write_camera", "Pose", "estimate_pose", "project_corners"]
