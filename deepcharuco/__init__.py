"""Deep ChArUco runtime: board geometry, detectors (deep and OpenCV) and pose.

    from deepcharuco import BoardSpec, OpenCVDetector
    det = OpenCVDetector(BoardSpec(), refine="subpix")
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

__version__ = "0.1.0"

__all__ = [
    "BoardSpec", "BoardTexture", "dictionary_names", "Camera", "read_camera", "write_camera",
    "Detection", "BoardSpecError", "CameraFileError", "DeepCharucoError", "ImageError",
    "CornerMatch", "match_corners", "OpenCVDetector", "Pose", "estimate_pose", "project_corners",
]


def __getattr__(name: str):
    if name == "Detector":
        # ImportError (not AttributeError) so that `from deepcharuco import Detector` shows this text.
        raise ImportError(
            "deepcharuco.Detector (ChArUcoNet + RefineNet) is not available in this version: "
            "the deep detector and its shipped weights are still being built; use "
            "deepcharuco.OpenCVDetector meanwhile"
        )
    raise AttributeError(f"module 'deepcharuco' has no attribute {name!r}")
