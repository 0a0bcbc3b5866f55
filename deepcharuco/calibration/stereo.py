"""A stereo pair's rectification (``cv2.stereoRectify``, ``cv2.fisheye.stereoRectify``), one camera's undistortion
(its new camera matrix), the undistort-rectify maps of either, and their files.

Conventions: poses x_b = R x_a + t in metres (`relative_pose`: camera a's frame to camera b's, as ``cv2.stereoRectify``
takes R and T); OpenCV's pixels. A rectified camera i sees the point x_i of its own frame at P_i (R_i x_i, 1): R_i
turns camera i onto the rectified frame, P_i (3 x 4) projects it; P2[0, 3] = -f' B puts the second camera B metres
along the rectified x axis, and Q maps (u, v, disparity, 1) to the point in the first rectified camera's frame.
Both are solved with alpha (pinhole) or balance (fisheye) 0: the rectified images show valid pixels only, as ROS's
stereo calibrator's default.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass

import cv2
import numpy as np

from deepcharuco.core.errors import ExportError
from deepcharuco.geometry.camera import Camera

GENERATOR = "deepcharuco calibrate --export opencv"


@dataclass(frozen=True)
class Rectification:
    """A stereo pair's rectification: ``R``, ``T`` camera 1 -> camera 2 (x2 = R x1 + T, metres); ``R1``, ``R2`` (3, 3)
    each camera's frame onto its rectified frame; ``P1``, ``P2`` (3, 4) the rectified cameras' projections; ``Q``
    (4, 4) disparity to depth (module docstring)."""

    R: np.ndarray
    T: np.ndarray
    R1: np.ndarray
    R2: np.ndarray
    P1: np.ndarray
    P2: np.ndarray
    Q: np.ndarray


def relative_pose(R_a: np.ndarray, t_a: np.ndarray, R_b: np.ndarray, t_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) from camera a's frame to camera b's (x_b = R x_a + t) of two poses x_cam = R_c X + t_c in one frame."""
    R = R_b @ R_a.T
    return R, np.asarray(t_b, np.float64).reshape(3) - R @ np.asarray(t_a, np.float64).reshape(3)


def check_pair(first: Camera, second: Camera, names: tuple[str, str]) -> None:
    """`ExportError` unless the two cameras can be rectified together: one model, one image size."""
    if first.model != second.model:
        raise ExportError(f"{names[0]} is a {first.model} camera and {names[1]} a {second.model} one: OpenCV rectifies "
                          f"a pair of one model; leave out --export opencv")
    if first.image_size != second.image_size:
        raise ExportError(f"{names[0]} is {first.image_size[0]}x{first.image_size[1]} and {names[1]} "
                          f"{second.image_size[0]}x{second.image_size[1]}: OpenCV rectifies a pair of one image size; "
                          f"leave out --export opencv")


def stereo_rectify(first: Camera, second: Camera, R: np.ndarray, T: np.ndarray,
                   names: tuple[str, str] = ("camera 1", "camera 2")) -> Rectification:
    """The pair's rectification (module docstring), camera 1 -> camera 2 being (``R``, ``T``); `ExportError` for a
    pair `check_pair` refuses."""
    check_pair(first, second, names)
    R = np.asarray(R, np.float64)
    T = np.asarray(T, np.float64).reshape(3, 1)
    if first.model == "fisheye":
        R1, R2, P1, P2, Q = cv2.fisheye.stereoRectify(first.K, first.dist, second.K, second.dist, first.image_size, R,
                                                      T, cv2.CALIB_ZERO_DISPARITY, balance=0.0, fov_scale=1.0)
    else:
        R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(first.K, first.dist, second.K, second.dist, first.image_size, R, T,
                                                    flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0)
    return Rectification(R, T.ravel(), R1, R2, P1, P2, Q)


def undistorted_matrix(camera: Camera) -> np.ndarray:
    """(3, 3) the camera matrix of the camera's undistorted image at its size, valid pixels only (alpha / balance 0:
    ``cv2.getOptimalNewCameraMatrix``, ``cv2.fisheye.estimateNewCameraMatrixForUndistortRectify``)."""
    if camera.model == "fisheye":
        return cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(camera.K, camera.dist, camera.image_size,
                                                                      np.eye(3), balance=0.0)
    return cv2.getOptimalNewCameraMatrix(camera.K, camera.dist, camera.image_size, 0.0)[0]


def rectify_maps(camera: Camera, R: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(map_x, map_y), each (H, W) float32: where in the camera's image each pixel of its rectified image (rotation
    ``R``, projection ``P`` (3, 3) or (3, 4)) lies, for ``cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR)``."""
    P = np.asarray(P, np.float64)[:, :3]
    init = cv2.fisheye.initUndistortRectifyMap if camera.model == "fisheye" else cv2.initUndistortRectifyMap
    return init(camera.K, camera.dist, np.asarray(R, np.float64), P, camera.image_size, cv2.CV_32FC1)


def _header(storage: cv2.FileStorage, cameras: list[Camera], names: list[str]) -> None:
    storage.write("generator", GENERATOR)
    storage.write("cameras", " ".join(names))
    storage.write("image_width", cameras[0].image_size[0])
    storage.write("image_height", cameras[0].image_size[1])
    storage.write("distortion_model", cameras[0].model)


def stereo_text(first: Camera, second: Camera, names: tuple[str, str], rectification: Rectification,
                name: str = "stereo.yaml") -> str:
    """OpenCV FileStorage with the nodes OpenCV's stereo_calib sample writes: ``M1`` ``D1`` ``M2`` ``D2`` (intrinsics),
    ``R`` ``T`` (camera 1 -> camera 2), ``R1`` ``R2`` ``P1`` ``P2`` ``Q``; and ``cameras``, the image size, the model."""
    storage = cv2.FileStorage(name, cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    _header(storage, [first, second], list(names))
    for key, value in (("M1", first.K), ("D1", first.dist.reshape(1, -1)), ("M2", second.K),
                       ("D2", second.dist.reshape(1, -1)), ("R", rectification.R), ("T", rectification.T.reshape(3, 1)),
                       ("R1", rectification.R1), ("R2", rectification.R2), ("P1", rectification.P1),
                       ("P2", rectification.P2), ("Q", rectification.Q)):
        storage.write(key, np.asarray(value, np.float64))
    return storage.releaseAndGetString()


def undistort_text(camera: Camera, name: str, file_name: str = "undistort.yaml") -> str:
    """One camera's OpenCV FileStorage: ``camera_matrix``, ``distortion_coefficients`` and ``new_camera_matrix``
    (`undistorted_matrix`: ``cv2.undistort(image, K, D, None, new_camera_matrix)``), the image size, the model."""
    storage = cv2.FileStorage(file_name, cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    _header(storage, [camera], [name])
    storage.write("camera_matrix", camera.K)
    storage.write("distortion_coefficients", camera.dist.reshape(1, -1))
    storage.write("new_camera_matrix", undistorted_matrix(camera))
    return storage.releaseAndGetString()


def maps_npz(maps: dict[str, tuple[np.ndarray, np.ndarray]]) -> bytes:
    """A compressed ``.npz`` (``numpy.load``) of each camera's maps: ``<name>_map_x``, ``<name>_map_y`` (H, W) float32,
    and ``generator``."""
    arrays = {"generator": np.array(json.dumps({"generator": GENERATOR, "cameras": list(maps)}))}
    for camera, (map_x, map_y) in maps.items():
        arrays[f"{camera}_map_x"], arrays[f"{camera}_map_y"] = map_x, map_y
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    return buffer.getvalue()


def is_maps_npz(path) -> bool:
    """Whether ``path`` is a `maps_npz` file (what ``--export opencv --rectify-maps`` may overwrite)."""
    with np.load(path, allow_pickle=False) as data:
        return "generator" in data.files and GENERATOR in str(data["generator"])
