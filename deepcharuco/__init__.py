"""Deep ChArUco runtime: board geometry, detectors (deep and OpenCV) and pose.

    from deepcharuco import BoardSpec, Detector, OpenCVDetector
    det = Detector(weights="detector.pt")     # or OpenCVDetector(BoardSpec(), refine="subpix")
    d = det.detect(gray_u8)                   # Detection: ids, corners, scores
    pose = det.estimate_pose(d, K, dist)      # Pose or None

The subpackages, bottom to top (each imports only those below it; docs/architecture.md):
`core`, `boards`, `geometry`, `networks`, `detection`, `calibration`, `cli`.
"""

from typing import TYPE_CHECKING

from deepcharuco.boards.board import BoardSpec, BoardTexture
from deepcharuco.boards.dictionaries import dictionary_names
from deepcharuco.core.detection import Detection
from deepcharuco.core.errors import BoardSpecError, CameraFileError, DeepCharucoError, ImageError, OptionError
from deepcharuco.core.version import __version__
from deepcharuco.detection.metrics import CornerMatch, match_corners
from deepcharuco.detection.opencv_detector import OpenCVDetector
from deepcharuco.detection.parallel import detect_all
from deepcharuco.detection.tracking import BoardTracker
from deepcharuco.geometry.camera import Camera, read_camera, write_camera
from deepcharuco.geometry.pose import Pose, estimate_pose, project_corners


__all__ = [
    "BoardSpec", "BoardTexture", "dictionary_names", "Camera", "read_camera", "write_camera",
    "Detection", "Detector", "BoardSpecError", "CameraFileError", "DeepCharucoError", "ImageError", "OptionError",
    "CornerMatch", "match_corners", "OpenCVDetector", "Pose", "estimate_pose", "project_corners", "BoardTracker",
    "detect_all",
]

if TYPE_CHECKING:
    from deepcharuco.detection.deep_detector import Detector


def __getattr__(name: str):
    # The deep detector loads its networks' runtime (ONNX Runtime, or PyTorch where asked): on first use, so that
    # `import deepcharuco` stays light (the Blender render workers import the board geometry through it).
    if name == "Detector":
        from deepcharuco.detection.deep_detector import Detector

        return Detector
    raise AttributeError(f"module 'deepcharuco' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | {"Detector"})
