"""Board pose from detected corners: RANSAC PnP, refinement and the paper's eps_re."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.core.checks import check_shape
from deepcharuco.core.detection import Detection
from deepcharuco.core.errors import OptionError, ShapeError
from deepcharuco.geometry.camera import DISTORTION_COUNTS, Camera, is_pinhole_matrix

# Below this ratio of the second to the first singular value the detected corners are
# (nearly) on one line, and the board's rotation about that line is not observable.
MIN_SPREAD_RATIO = 0.05


@dataclass(frozen=True)
class Pose:
    """A board pose (board -> camera, OpenCV axes) and how well it explains the detection.

    Attributes:
        rvec: (3,) float64 Rodrigues rotation.
        tvec: (3,) float64 translation in metres.
        reprojection_error: the paper's eps_re, the mean distance in pixels between each
            detected corner and its reprojection, over all detected corners.
        inliers: (M,) int64 corner IDs that RANSAC kept (ascending).
        residuals: (N,) float64 reprojection error of each detected corner, in detection order.
    """

    rvec: np.ndarray
    tvec: np.ndarray
    reprojection_error: float
    inliers: np.ndarray
    residuals: np.ndarray

    def to_dict(self) -> dict:
        return {
            "rvec": self.rvec.tolist(),
            "tvec": self.tvec.tolist(),
            "reprojection_error": float(self.reprojection_error),
            "inliers": self.inliers.tolist(),
        }


def project_corners(
    board: BoardSpec, rvec: np.ndarray, tvec: np.ndarray, K: np.ndarray, dist: np.ndarray | None = None,
    ids: np.ndarray | None = None,
) -> np.ndarray:
    """(N, 2) float64 image positions (OpenCV's pixel convention) of the board's inner corners (all, or ``ids``,
    in that order) under a pose (board -> camera, ``tvec`` in metres).

    Example:
        >>> board = BoardSpec()  # the paper's board: 5 x 5 squares of 4 cm, 16 inner corners
        >>> K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
        >>> project_corners(board, np.zeros(3), np.array([-0.05, -0.05, 0.5]), K, ids=[0, 1]).round(2)
        array([[304., 224.],
               [368., 224.]])
    """
    points = board.object_points()
    if ids is not None:
        points = points[np.asarray(ids, dtype=np.int64)]
    if points.shape[0] == 0:
        return np.zeros((0, 2))
    image_points, _ = cv2.projectPoints(
        points, np.asarray(rvec, np.float64), np.asarray(tvec, np.float64),
        np.asarray(K, np.float64), None if dist is None else np.asarray(dist, np.float64),
    )
    return image_points.reshape(-1, 2)


def check_camera_matrix(K) -> np.ndarray:
    """``K`` as a (3, 3) float64 pinhole camera matrix, or `ShapeError`: not finite (3, 3), fx or fy not positive, or
    a last row other than 0 0 1 (a transposed matrix fits a pose 3 px from its corners, far from the truth)."""
    K = check_shape(K, (3, 3), "K")
    if not is_pinhole_matrix(K):
        raise ShapeError(f"K is not a pinhole camera matrix (fx, fy > 0, last row 0 0 1; transposed?):\n{K}")
    return K


def check_distortion(dist) -> np.ndarray:
    """``dist`` as OpenCV's pinhole distortion coefficients (4, 5, 8, 12 or 14 finite values; any shape of them), or
    `ShapeError` naming the count."""
    dist = check_shape(np.ravel(np.asarray(dist, np.float64)), (None,), "dist")
    if dist.size not in DISTORTION_COUNTS:
        raise ShapeError(f"dist holds {dist.size} coefficients: OpenCV's models take 4, 5, 8, 12 or 14")
    return dist


def estimate_pose(
    detection: Detection,
    K: np.ndarray | Camera,
    dist: np.ndarray | None = None,
    board: BoardSpec | None = None,
    *,
    ransac_threshold: float = 3.0,
    min_inliers: int = 4,
) -> Pose | None:
    """Board pose by ``cv2.solvePnPRansac`` (IPPE, planar) then Levenberg-Marquardt on the inliers.

    Args:
        detection: corners of ``board`` (IDs index ``board.corner_points()``).
        K: (3, 3) camera matrix (fx, fy > 0, last row 0 0 1) with ``dist`` OpenCV's pinhole distortion coefficients
            (4, 5, 8, 12 or 14) or None; or a `Camera` (``dist`` left out), whose model is then used: a fisheye
            camera's corners are undistorted first and its reprojection error measured through its own model (its
            k1..k4 given as ``dist`` would read as k1 k2 p1 p2).
        board: the board the IDs refer to (required: the IDs alone do not say which board, and another board's
            squares put the pose at another distance; a detector's own ``estimate_pose`` passes its board).
        ransac_threshold: RANSAC inlier threshold in pixels.
        min_inliers: fewest inliers for a pose to be returned.

    Returns:
        The `Pose`, or None when fewer than 4 corners were detected, the corners lie on a
        line (rotation unobservable), RANSAC finds no consensus of ``min_inliers``, or the
        board would be behind the camera.

    Raises:
        ShapeError: ``K`` is not a finite pinhole (3, 3) matrix, or ``dist`` not 4, 5, 8, 12 or 14 finite values.
        OptionError: no ``board``, or the detection's IDs are not corners of it.

    Example:
        >>> board = BoardSpec()
        >>> K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
        >>> corners = project_corners(board, np.zeros(3), np.array([-0.05, -0.05, 0.5]), K)
        >>> found = Detection(ids=np.arange(16), corners=corners, scores=np.ones(16))
        >>> pose = estimate_pose(found, K, None, board)
        >>> pose.tvec.round(4), round(pose.reprojection_error, 3)
        (array([-0.05, -0.05,  0.5 ]), 0.0)
    """
    if board is None:
        raise OptionError("estimate_pose needs board=, the board the detection's corner IDs refer to: the IDs alone do "
                          "not say which board, and another board's squares put the pose at another distance")
    camera = K if isinstance(K, Camera) else None
    if camera is not None:
        if dist is not None:
            raise OptionError("give a Camera alone (its dist is its own), or K and dist, not a Camera and dist")
        K, dist = camera.K, (None if camera.model == "fisheye" else camera.dist)
    K = check_camera_matrix(K)
    dist = None if dist is None else check_distortion(dist)
    if len(detection) < 4:
        return None
    if detection.ids.min() < 0 or detection.ids.max() >= board.num_corners:
        raise OptionError(
            f"corner IDs {detection.ids.tolist()} do not belong to a board with {board.num_corners} "
            "corners: pass the board the detection was made for"
        )
    object_points = board.object_points()[detection.ids]
    detected = detection.corners.astype(np.float64)
    fisheye = camera is not None and camera.model == "fisheye"
    image_points = camera.undistort_points(detected) if fisheye else detected  # solvePnP knows the pinhole model
    spread = np.linalg.svd(object_points[:, :2] - object_points[:, :2].mean(0), compute_uv=False)
    if spread[1] < MIN_SPREAD_RATIO * spread[0]:
        return None
    found, rvec, tvec, inlier_idx = cv2.solvePnPRansac(
        object_points, image_points, K, dist,
        reprojectionError=ransac_threshold, iterationsCount=200, confidence=0.999, flags=cv2.SOLVEPNP_IPPE,
    )
    if not found or inlier_idx is None or len(inlier_idx) < min_inliers:
        return None
    inlier_idx = np.sort(inlier_idx.ravel())
    rvec, tvec = cv2.solvePnPRefineLM(object_points[inlier_idx], image_points[inlier_idx], K, dist, rvec, tvec)
    rvec, tvec = rvec.ravel(), tvec.ravel()
    rotation, _ = cv2.Rodrigues(rvec)
    depths = (object_points @ rotation.T + tvec)[:, 2]
    if np.any(depths <= 0):
        return None
    reprojected = camera.project(object_points, rvec, tvec) if fisheye else \
        project_corners(board, rvec, tvec, K, dist, detection.ids)
    residuals = np.linalg.norm(reprojected - detected, axis=1)  # in the frame's pixels, through the camera's model
    return Pose(
        rvec=rvec,
        tvec=tvec,
        reprojection_error=float(residuals.mean()),
        inliers=detection.ids[inlier_idx],
        residuals=residuals,
    )
