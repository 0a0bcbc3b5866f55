"""Detection: the deep detector (ChArUcoNet's cells, the coarse-to-fine search, marker reading, the board placed
from its markers, the printed-pattern corner fit) and OpenCV's, tracking through a video, worker processes, and
the hints given when the board file does not match the board seen.

Imports `deepcharuco.core`, `boards`, `geometry` and `networks`. The names here are loaded on first use.
"""

from typing import TYPE_CHECKING

from deepcharuco.core.lazy import lazy_exports

_WHERE = {
    "Detector": "deep_detector", "OpenCVDetector": "opencv_detector", "BoardTracker": "tracking",
    "detect_all": "parallel", "DetectorPool": "parallel", "CornerMatch": "metrics", "match_corners": "metrics",
}
__all__ = list(_WHERE)
__getattr__, __dir__ = lazy_exports(__name__, _WHERE)

if TYPE_CHECKING:
    from deepcharuco.detection.deep_detector import Detector
    from deepcharuco.detection.metrics import CornerMatch, match_corners
    from deepcharuco.detection.opencv_detector import OpenCVDetector
    from deepcharuco.detection.parallel import DetectorPool, detect_all
    from deepcharuco.detection.tracking import BoardTracker
