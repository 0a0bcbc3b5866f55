"""Labels of a rendered board: its inner corners and its markers, through a (possibly distorted) camera.

Plain numpy and OpenCV. A point of the printed board is projected where the camera sees it:
on the sheet as rendered (`datagen.scene.bent_points`: a bent print moves points along the
board's Z), through OpenCV's camera model (K and, for a distorted frame, its distortion
coefficients: ``cv2.projectPoints``, which `datagen.lens` renders exactly). Pixel convention:
OpenCV's (the centre of the top-left pixel is (0, 0)); a point is *inside* the image when it
lies on a pixel of it, i.e. in [-0.5, W - 0.5) x [-0.5, H - 0.5).
"""

from __future__ import annotations

import cv2
import numpy as np

from datagen.scene import SceneSpec, bent_points
from datagen.shards import MarkerLabels
from deepcharuco.boards.board import BoardSpec


def marker_points(board: BoardSpec) -> tuple[np.ndarray, np.ndarray]:
    """(ids (M,) int64, points (M, 5, 3) float64): each marker's four corners in OpenCV's order (clockwise
    from the printed marker's top-left, as ``cv2.aruco`` returns them) and its centre, in the board frame
    where the camera sees them: mirrored left-right (X -> width - X) for a ``mirrored`` board, as
    `BoardSpec.object_points` does for the corners."""
    ids, corners = board.marker_corners()
    points = np.concatenate([corners, corners.mean(axis=1, keepdims=True)], axis=1)
    if board.mirrored:
        points[:, :, 0] = board.size_m[0] - points[:, :, 0]
    return ids, points


def project(points: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, K: np.ndarray,
            dist: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) board-frame points -> (pixels (N, 2) float64, NaN behind the camera; in_front (N,) bool)."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if points.shape[0] == 0:
        return np.zeros((0, 2)), np.zeros(0, bool)
    pixels, _ = cv2.projectPoints(points, np.asarray(rvec, np.float64), np.asarray(tvec, np.float64),
                                  np.asarray(K, np.float64), None if dist is None else np.asarray(dist, np.float64))
    pixels = pixels.reshape(-1, 2)
    in_front = ((points @ cv2.Rodrigues(np.asarray(rvec, np.float64))[0].T)[:, 2] + tvec[2]) > 1e-6
    pixels[~in_front] = np.nan
    return pixels, in_front


def inside_image(pixels: np.ndarray, width: int, height: int) -> np.ndarray:
    """(..., 2) pixels -> (...) bool: on a pixel of the W x H image (NaN: False)."""
    x, y = pixels[..., 0], pixels[..., 1]
    with np.errstate(invalid="ignore"):
        return (x >= -0.5) & (x < width - 0.5) & (y >= -0.5) & (y < height - 0.5)


def label_corners(board: BoardSpec, spec: SceneSpec, rvec: np.ndarray, tvec: np.ndarray, unoccluded: np.ndarray,
                  dist: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(corners (C, 2) float32, visible (C,) bool) of the board in ``spec``'s camera (K, width, height) with
    ``dist``: NaN behind the camera; visible = inside the image and ``unoccluded`` (C,) (ray casts)."""
    points = bent_points(board.object_points(), spec, board.size_m)
    pixels, in_front = project(points, rvec, tvec, spec.K, dist)
    corners = pixels.astype(np.float32)
    return corners, in_front & inside_image(corners, spec.width, spec.height) & np.asarray(unoccluded, bool)


def label_markers(board: BoardSpec, spec: SceneSpec, rvec: np.ndarray, tvec: np.ndarray,
                  unoccluded: np.ndarray | None, dist: np.ndarray | None = None) -> MarkerLabels:
    """Every marker of the board in ``spec``'s camera with ``dist``: IDs, corners, centres (the projection of
    the marker's centre point, not the mean of its projected corners) and visibility = its four corners and
    its centre inside the image, in front of the camera and unoccluded (``unoccluded``: (M, 5) ray casts in
    `marker_points`' order; None: all occluded, as for a negative frame)."""
    ids, points = marker_points(board)
    count = len(ids)
    points = bent_points(points.reshape(-1, 3), spec, board.size_m)
    pixels, in_front = project(points, rvec, tvec, spec.K, dist)
    pixels = pixels.reshape(count, 5, 2).astype(np.float32)
    seen = (in_front.reshape(count, 5) & inside_image(pixels, spec.width, spec.height)
            & (np.zeros((count, 5), bool) if unoccluded is None else np.asarray(unoccluded, bool).reshape(count, 5)))
    return MarkerLabels(ids=ids.astype(np.int32), corners=np.ascontiguousarray(pixels[:, :4]),
                        centres=np.ascontiguousarray(pixels[:, 4]), visible=seen.all(axis=1))


def no_markers(board: BoardSpec) -> MarkerLabels:
    """The marker labels of a frame that does not show ``board`` (a negative): IDs, NaN positions, none visible."""
    ids, _ = board.marker_corners()
    count = len(ids)
    return MarkerLabels(ids=ids.astype(np.int32), corners=np.full((count, 4, 2), np.nan, np.float32),
                        centres=np.full((count, 2), np.nan, np.float32), visible=np.zeros(count, bool))
