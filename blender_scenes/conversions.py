"""OpenCV <-> Blender camera conventions, in plain numpy (no bpy: testable anywhere).

Facts from BLENDER_NOTES.md, verified there to < 0.04 px against ``cv2.projectPoints``:
with ``sensor_fit = 'HORIZONTAL'``, image width W and height H,

    lens    = fx * sensor_width / W
    shift_x = -(cx + 0.5 - W/2) / W
    shift_y =  (cy + 0.5 - H/2) * par / W          par = pixel_aspect_y / pixel_aspect_x

(the +0.5: Blender's first pixel centre is raster 0.5, OpenCV's is 0), and a Blender camera
looks down its -Z with +Y up, so its world matrix is OpenCV's camera-to-world @ diag(1,-1,-1,1).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

SENSOR_WIDTH_MM = 36.0
CV_TO_BLENDER_CAMERA = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class BlenderCameraParams:
    """What a Blender camera needs to reproduce an OpenCV K (no distortion)."""

    lens_mm: float
    sensor_width_mm: float
    shift_x: float
    shift_y: float
    pixel_aspect_x: float
    pixel_aspect_y: float
    width: int
    height: int


def blender_camera_from_K(K: np.ndarray, width: int, height: int, sensor_width_mm: float = SENSOR_WIDTH_MM) -> BlenderCameraParams:
    """Blender camera settings for the (3, 3) intrinsics ``K`` at ``width`` x ``height``."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or abs(K[0, 1]) > 1e-9 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"K must be a 3x3 pinhole matrix with positive focal lengths and no skew, got {K.tolist()}")
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if fy > fx * (1 + 1e-9):
        # Measured: Blender renders such a camera up to 0.8 px away from this formula's K (fine for fx >= fy).
        raise ValueError(f"fy ({fy:.3f}) > fx ({fx:.3f}) is not supported by the Blender conversion; use fy <= fx")
    aspect_x, aspect_y = (1.0, fx / fy) if fx > fy else (fy / fx, 1.0)
    par = aspect_y / aspect_x
    return BlenderCameraParams(
        lens_mm=fx * sensor_width_mm / width,
        sensor_width_mm=sensor_width_mm,
        shift_x=-(cx + 0.5 - width / 2.0) / width,
        shift_y=(cy + 0.5 - height / 2.0) * par / width,
        pixel_aspect_x=aspect_x,
        pixel_aspect_y=aspect_y,
        width=int(width),
        height=int(height),
    )


def K_from_blender_camera(params: BlenderCameraParams) -> np.ndarray:
    """The inverse of `blender_camera_from_K`: (3, 3) intrinsics."""
    w, h = params.width, params.height
    par = params.pixel_aspect_y / params.pixel_aspect_x
    fx = params.lens_mm * w / params.sensor_width_mm
    return np.array([
        [fx, 0.0, w / 2.0 - 0.5 - params.shift_x * w],
        [0.0, fx / par, h / 2.0 - 0.5 + params.shift_y * w / par],
        [0.0, 0.0, 1.0],
    ])


def blender_camera_matrix(world_from_cv_camera: np.ndarray) -> np.ndarray:
    """(4, 4) Blender camera object matrix from an OpenCV camera-to-world transform."""
    return np.asarray(world_from_cv_camera, dtype=np.float64) @ CV_TO_BLENDER_CAMERA


def cv_camera_from_blender(blender_matrix: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-world transform from a Blender camera object matrix."""
    return np.asarray(blender_matrix, dtype=np.float64) @ CV_TO_BLENDER_CAMERA


def rigid(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(4, 4) transform from a (3, 3) rotation and a (3,) translation.

    Raises ValueError for a matrix that is not a proper rotation: Blender would render its nearest
    rotation while labels used the matrix itself."""
    rotation = np.asarray(rotation, dtype=np.float64)
    if rotation.shape != (3, 3) or not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-6) \
            or np.linalg.det(rotation) <= 0:
        raise ValueError(f"rotation must be a proper 3x3 rotation (orthonormal, det +1), got {rotation.tolist()}")
    matrix = np.eye(4)
    matrix[:3, :3] = rotation
    matrix[:3, 3] = np.ravel(translation)
    return matrix


def board_pose_in_camera(world_from_cv_camera: np.ndarray, world_from_board: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV (rvec, tvec), board -> camera, of a board and a camera both placed in the world."""
    camera_from_board = np.linalg.inv(world_from_cv_camera) @ world_from_board
    rvec, _ = cv2.Rodrigues(camera_from_board[:3, :3])
    return rvec.ravel(), camera_from_board[:3, 3].copy()
