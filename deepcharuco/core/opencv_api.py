"""The calls whose names or constants differ between OpenCV 4 and OpenCV 5, each behind one function.

OpenCV 5 folded ``cv2.undistortPointsIter`` (OpenCV 4's name for `undistortPoints` with a stopping criterion) into
``cv2.undistortPoints(..., criteria=)`` and moved the fisheye model's calibration flags from ``cv2.fisheye.CALIB_*``
to the common ``cv2.CALIB_*`` (with other values). The runtime accepts both (pyproject: opencv >= 4.10).
"""

from __future__ import annotations

import cv2
import numpy as np


def undistort_points(points: np.ndarray, K: np.ndarray, dist: np.ndarray, P: np.ndarray | None,
                     criteria: tuple[int, int, float]) -> np.ndarray:
    """``cv2.undistortPoints`` of (N, 1, 2) ``points`` iterated to ``criteria`` (OpenCV 4: ``undistortPointsIter``):
    (N, 1, 2) normalised coordinates, or pixels of ``P``."""
    if hasattr(cv2, "undistortPointsIter"):
        return cv2.undistortPointsIter(points, K, dist, None, P, criteria)
    return cv2.undistortPoints(points, K, dist, R=None, P=P, criteria=criteria)


def fisheye_calibration_flags() -> int:
    """``cv2.fisheye.calibrate``'s flags: recompute the views' poses each iteration, no skew."""
    fisheye = cv2.fisheye
    if hasattr(fisheye, "CALIB_RECOMPUTE_EXTRINSIC"):
        return fisheye.CALIB_RECOMPUTE_EXTRINSIC | fisheye.CALIB_FIX_SKEW
    return cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW


def fisheye_flag(name: str) -> int:
    """One of ``cv2.fisheye.calibrate``'s flags by its name without ``CALIB_`` (e.g. "FIX_K1"): OpenCV 4's
    ``cv2.fisheye.CALIB_FIX_K1``, OpenCV 5's ``cv2.CALIB_FIX_K1``."""
    return int(getattr(cv2.fisheye, f"CALIB_{name}", None) or getattr(cv2, f"CALIB_{name}"))


def log_errors_only() -> None:
    """OpenCV's own log messages: errors only (OpenCV 4: ``cv2.setLogLevel``; 5: ``cv2.utils.logging``)."""
    logging = getattr(getattr(cv2, "utils", None), "logging", None)
    if logging is not None and hasattr(logging, "setLogLevel"):
        logging.setLogLevel(logging.LOG_LEVEL_ERROR)
    else:
        cv2.setLogLevel(2)  # OpenCV 4's LOG_LEVEL_ERROR
