"""The paper's baseline: OpenCV's ChArUco detector, optionally followed by cornerSubPix."""

from __future__ import annotations

import warnings
from functools import cache

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.boards.print_face import canonical_view, corners_from_canonical
from deepcharuco.boards.synthetic import look_at_pose, render_board_view
from deepcharuco.core.checks import check_choice
from deepcharuco.core.detection import Detection, detect_board_result
from deepcharuco.core.errors import OptionError
from deepcharuco.core.image import to_gray_u8
from deepcharuco.geometry.pose import Pose, estimate_pose, project_corners

REFINE_MODES = ("subpix", "none")
MIN_WINDOW = 2  # cornerSubPix's smallest half-window (px) for "subpix"


@cache
def charuco_detector_bias() -> np.ndarray:
    """(2,) float32 constant offset of ``CharucoDetector.detectBoard`` corners in this OpenCV.

    OpenCV 4.7-4.12 shift every ChArUco corner by (+0.5, +0.5) px (opencv/opencv#25539: a
    half-pixel shift around its internal cornerSubPix, fixed in #28380). Rather than trust a
    version number, measure it once on an exact synthetic view and round to half pixels.
    """
    board = BoardSpec()
    K = np.array([[280.0, 0.0, 159.5], [0.0, 280.0, 119.5], [0.0, 0.0, 1.0]])
    rvec, tvec = look_at_pose(board, 0.35, tilt_x_deg=20.0, tilt_y_deg=-15.0, roll_deg=10.0)
    image = render_board_view(board, K, rvec, tvec, (320, 240))
    corners, ids, _, _ = cv2.aruco.CharucoDetector(board.cv_board()).detectBoard(image)
    if ids is None or len(ids) < board.num_corners // 2:
        warnings.warn("OpenCV's ChArUco detector failed on a clean synthetic view; assuming it has no "
                      "half-pixel bias", RuntimeWarning, stacklevel=2)
        return np.zeros(2, np.float32)
    offset = corners.reshape(-1, 2) - project_corners(board, rvec, tvec, K, ids=ids.ravel())
    return (np.round(np.median(offset, axis=0) * 2.0) / 2.0).astype(np.float32)


class OpenCVDetector:
    """``cv2.aruco.CharucoDetector`` behind the project's detector interface.

    Args:
        board: the board to find; default the paper's board.
        refine: ``"none"`` returns OpenCV's corners as OpenCV computes them (it already runs
            a coarse cornerSubPix, 30 iterations to 0.1 px, when it interpolates corners from
            markers), less the half-pixel bias of OpenCV 4.7-4.12 (`charuco_detector_bias`).
            ``"subpix"`` — the paper's "OpenCV + cornerSubPix" baseline — adds an explicit
            cornerSubPix pass converged to 0.001 px, with each corner's window kept clear of
            the nearest detected marker corner as OpenCV does (half-window at least `MIN_WINDOW`, or
            ``max_window`` where that is smaller).
        max_window: the largest cornerSubPix half-window (px) for ``"subpix"``.
    """

    def __init__(self, board: BoardSpec | None = None, refine: str = "subpix", max_window: int = 5):
        check_choice("refine", refine, REFINE_MODES)
        if max_window < 1:
            raise OptionError(f"max_window must be >= 1 px, got {max_window}")
        self.board = board or BoardSpec()
        self.refine = refine
        self.max_window = int(max_window)
        self._detector = cv2.aruco.CharucoDetector(self.board.cv_board())

    def __repr__(self) -> str:
        return f"OpenCVDetector(board={self.board!r}, refine={self.refine!r})"

    def detect(self, image: np.ndarray) -> Detection:
        """Find the board's corners in a uint8 grayscale (or BGR) image."""
        return self._detect(image)[0]

    def detectBoard(self, image: np.ndarray):  # noqa: N802 - OpenCV's name, so that scripts switch in one line
        """What ``cv2.aruco.CharucoDetector.detectBoard`` returns: (charuco corners (N, 1, 2) float32, charuco ids
        (N, 1) int32; None for both when none are found; marker corners, a tuple of (1, 4, 2) float32; marker ids
        (M, 1) int32 or None), with this detector's refinement and without OpenCV 4.11's half-pixel bias."""
        detection, marker_corners, marker_ids = self._detect(image)
        return detect_board_result(detection, marker_corners, marker_ids)

    def _detect(self, image: np.ndarray) -> tuple[Detection, tuple, np.ndarray | None]:
        gray = canonical_view(to_gray_u8(image), self.board)  # OpenCV finds only the canonical print
        corners, ids, canonical_markers, marker_ids = self._detector.detectBoard(gray)
        width = gray.shape[1]
        marker_corners = tuple(corners_from_canonical(m.reshape(-1, 2), self.board, width).reshape(1, 4, 2)
                               .astype(np.float32) for m in canonical_markers)
        if ids is None or len(ids) == 0:
            return Detection.empty(), marker_corners, marker_ids
        corners = corners.reshape(-1, 2).astype(np.float32) - charuco_detector_bias()
        if self.refine == "subpix":
            corners = self._subpix(gray, corners, np.concatenate([m.reshape(-1, 2) for m in canonical_markers]))
        corners = corners_from_canonical(corners, self.board, width)
        detection = Detection(ids=ids.ravel(), corners=corners, scores=np.ones(len(corners), np.float32))
        return detection, marker_corners, marker_ids

    def _subpix(self, gray: np.ndarray, corners: np.ndarray, marker_points: np.ndarray) -> np.ndarray:
        # A window that reaches a marker corner pulls the estimate towards it: keep 2 px clear, but no smaller than
        # MIN_WINDOW: a 3x3 window on squares under ~15 px left 10 % of the corners > 0.5 px off (validation views
        # of evaluate.calibration.corner_precision, seed 0: small squares p90 0.69 -> 0.24 px, oblique 0.22 -> 0.15, the rest
        # unchanged).
        nearest = np.linalg.norm(corners[:, None, :] - marker_points[None, :, :], axis=2).min(axis=1)
        windows = np.clip((nearest - 2.0).astype(int), min(MIN_WINDOW, self.max_window), self.max_window)
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 0.001)
        refined = corners.copy()
        for window in np.unique(windows):
            chosen = windows == window
            refined[chosen] = cv2.cornerSubPix(
                gray, corners[chosen].reshape(-1, 1, 2).copy(), (int(window), int(window)), (-1, -1), criteria
            ).reshape(-1, 2)
        return refined

    def estimate_pose(self, detection: Detection, K: np.ndarray, dist: np.ndarray | None = None, **kwargs) -> Pose | None:
        """`deepcharuco.estimate_pose` for this detector's board."""
        return estimate_pose(detection, K, dist, board=self.board, **kwargs)
