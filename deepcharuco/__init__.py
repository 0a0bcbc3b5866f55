"""Deep ChArUco runtime: board geometry, detectors (deep and OpenCV) and pose.

    from deepcharuco import BoardSpec, Detector, OpenCVDetector
    det = Detector(weights="detector.pt")     # or OpenCVDetector(BoardSpec(), refine="subpix")
    d = det.detect(gray_u8)                   # Detection: ids, corners, scores
    pose = det.estimate_pose(d, K, dist)      # Pose or None
"""

from deepcharuco.board import BoardSpec, BoardTexture, dictionary_names
from deepcharuco.camera import Camera, read_camera, write_camera
from deepcharuco.detection import Detection
from deepcharuco.errors import BoardSpecError, CameraFileError, DeepCharucoError, ImageError
from deepcharuco.metrics import CornerMatch, match_corners
from deepcharuco.opencv_detector import OpenCVDetector
from deepcharuco.pose import Pose, estimate_pose, project_corners
from deepcharuco.tracking import BoardTracker

__version__ = "0.1.0"

__all__ = [
    "BoardSpec", "BoardTexture", "dictionary_names", "Camera", "read_camera", "write_camera",
    "Detection", "Detector", "BoardSpecError", "CameraFileError", "DeepCharucoError", "ImageError",
    "CornerMatch", "match_corners", "OpenCVDetector", "Pose", "estimate_pose", "project_corners", "BoardTracker",
]


def __getattr__(name: str):
    # The deep detector imports torch: loaded on first use, so `import deepcharuco` stays light
    # (the Blender render workers import the board geometry and must not pull torch in).
    if name == "Detector":
        from deepcharuco.deep_detector import Detector

        return Detector
    raise AttributeError(f"module 'deepcharuco' has no attribute {name!r}")
