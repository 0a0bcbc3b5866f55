"""Camera intrinsics (OpenCV's pinhole model with its distortion, or OpenCV's fisheye model) and their
OpenCV FileStorage YAML files."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from deepcharuco.core.errors import CameraFileError
from deepcharuco.core.files import write_atomic
from deepcharuco.core.opencv_api import undistort_points

# "pinhole": OpenCV's standard model (cv2.projectPoints; 4, 5, 8, 12 or 14 coefficients, the rational
# model included); "fisheye": cv2.fisheye's equidistant model (k1..k4), which cv2.projectPoints would
# misread as k1 k2 p1 p2.
CAMERA_MODELS = ("pinhole", "fisheye")
DISTORTION_COUNTS = (0, 4, 5, 8, 12, 14)  # OpenCV's pinhole models' coefficients (0: none)


def is_pinhole_matrix(K: np.ndarray) -> bool:
    """Whether the finite (3, 3) ``K`` is a camera matrix: fx, fy > 0 and a last row 0 0 1 (a transposed one is not)."""
    return bool(K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[2], (0.0, 0.0, 1.0)))


@dataclass(frozen=True)
class Camera:
    """OpenCV intrinsics for images of ``image_size`` = (width, height) pixels.

    Attributes:
        K: (3, 3) float64 camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]].
        dist: (D,) float64 OpenCV distortion coefficients: (k1, k2, p1, p2[, k3, ...]) for the
            "pinhole" model, (k1, k2, k3, k4) for "fisheye".
        image_size: (width, height) in pixels the intrinsics belong to.
        model: "pinhole" (OpenCV's standard model) or "fisheye" (``cv2.fisheye``).
    """

    K: np.ndarray
    dist: np.ndarray
    image_size: tuple[int, int]
    model: str = "pinhole"

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise CameraFileError(f"camera_matrix must be a finite 3x3 matrix, got shape {K.shape}")
        if not is_pinhole_matrix(K):
            raise CameraFileError(f"camera_matrix is not a pinhole matrix (fx, fy > 0, last row 0 0 1):\n{K}")
        dist = np.asarray(self.dist if self.dist is not None else np.zeros(5), dtype=np.float64).reshape(-1)
        if dist.size not in DISTORTION_COUNTS or not np.all(np.isfinite(dist)):
            raise CameraFileError(
                f"distortion_coefficients must hold 4, 5, 8, 12 or 14 finite values, got {dist.size}"
            )
        if self.model not in CAMERA_MODELS:
            raise CameraFileError(f"distortion_model must be one of {', '.join(CAMERA_MODELS)}, got {self.model!r}")
        if self.model == "fisheye" and dist.size != 4:
            raise CameraFileError(f"a fisheye camera has 4 distortion coefficients (k1..k4), got {dist.size}")
        width, height = (int(v) for v in self.image_size)
        if width <= 0 or height <= 0:
            raise CameraFileError(f"image size must be positive, got {self.image_size}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "image_size", (width, height))

    @classmethod
    def from_fov(cls, width: int = 320, height: int = 240, hfov_deg: float = 60.0) -> "Camera":
        """An undistorted camera with square pixels, centred principal point and the given FOV."""
        fx = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        K = np.array([[fx, 0.0, (width - 1) / 2.0], [0.0, fx, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
        return cls(K=K, dist=np.zeros(5), image_size=(width, height))

    def scaled(self, width: int, height: int) -> "Camera":
        """Intrinsics of the same camera with its images resized to (width, height).

        Pixel centres follow OpenCV's convention (top-left pixel centre at (0, 0)), so a
        point at u maps to (u + 0.5) * sx - 0.5: fx' = sx fx, cx' = sx (cx + 0.5) - 0.5 —
        exactly what ``cv2.resize`` does to the image. Distortion is scale-free.
        """
        sx = width / self.image_size[0]
        sy = height / self.image_size[1]
        K = self.K.copy()
        K[0, 0] *= sx
        K[0, 1] *= sx
        K[0, 2] = sx * (K[0, 2] + 0.5) - 0.5
        K[1, 1] *= sy
        K[1, 2] = sy * (K[1, 2] + 0.5) - 0.5
        return Camera(K=K, dist=self.dist.copy(), image_size=(width, height), model=self.model)

    def for_image_size(self, width: int, height: int) -> "Camera":
        """These intrinsics for frames of (width, height): themselves, or `scaled` when the frames are
        resized; `CameraFileError` when the aspect ratio differs (a crop cannot be undone by scaling)."""
        if (width, height) == self.image_size:
            return self
        cw, ch = self.image_size
        if abs(width / height - cw / ch) > 0.01:
            why = "rotated (portrait against landscape?)" if abs(width / height - ch / cw) <= 0.01 else "cropped?"
            raise CameraFileError(
                f"frames are {width}x{height} but the camera file is for {cw}x{ch}, a different aspect "
                f"ratio ({why}): calibrate at this resolution"
            )
        return self.scaled(width, height)


    def project(self, object_points: np.ndarray, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
        """(N, 2) pixels of the (N, 3) points under the pose (rvec, tvec), through this camera's model."""
        points = np.asarray(object_points, np.float64).reshape(-1, 1, 3)
        rvec = np.asarray(rvec, np.float64).reshape(3, 1)
        tvec = np.asarray(tvec, np.float64).reshape(3, 1)
        if self.model == "fisheye":
            pixels, _ = cv2.fisheye.projectPoints(points, rvec, tvec, self.K, self.dist)
        else:
            pixels, _ = cv2.projectPoints(points, rvec, tvec, self.K, self.dist)
        return pixels.reshape(-1, 2)

    def undistort_points(self, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) where the (N, 2) distorted pixels would lie in an undistorted image with the same K: what a
        pinhole-only consumer (``cv2.solvePnP`` with no distortion) of a fisheye camera's corners needs."""
        points = np.asarray(pixels, np.float64).reshape(-1, 1, 2)
        if len(points) == 0:
            return np.zeros((0, 2))
        # OpenCV's default criteria stop 1e-3 px short on a strong lens; 50 iterations to 1e-10 cost nothing.
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
        if self.model == "fisheye":
            undistorted = cv2.fisheye.undistortPoints(points, self.K, self.dist, R=np.eye(3), P=self.K, criteria=criteria)
        else:
            undistorted = undistort_points(points, self.K, self.dist, self.K, criteria)
        return undistorted.reshape(-1, 2)


def read_camera(path: str | Path) -> Camera:
    """Read intrinsics from an OpenCV FileStorage file (YAML/XML/JSON), as calibration writes them, or from a ROS
    ``camera_info`` YAML (as ``calibrate --export ros`` and ROS's camera_calibration write it).

    Required nodes: ``camera_matrix``, ``image_width`` and ``image_height``; optional
    ``distortion_coefficients`` (zeros when absent) and ``distortion_model`` ("fisheye" for
    ``cv2.fisheye``'s model; "pinhole", "rational" or absent for OpenCV's standard one; ROS's plumb_bob,
    rational_polynomial and equidistant).

    Raises:
        CameraFileError: a missing or unreadable file, a file that is not a camera file, or intrinsics that are
            not a camera (a non-positive focal length, NaN), with what to do.
    """
    path = Path(path)
    if not path.is_file():
        raise CameraFileError(f"camera file {path} does not exist: calibrate the camera first (python -m "
                              f"deepcharuco.cli.calibrate VIDEO --board board.yaml --out {path})")

    def ros_or_refused(exc: Exception) -> Camera:
        """The file as a ROS camera_info YAML (which OpenCV's parser refuses without its header), else refused."""
        ros = _ros_camera_info(path)
        if ros is None:
            raise CameraFileError(f"{path} is not an OpenCV FileStorage file ({exc.__class__.__name__}); it must start "
                                  f"with '%YAML:1.0' (OpenCV 5: '%YAML 1.2') and hold camera_matrix as an "
                                  f"opencv-matrix") from exc
        return ros

    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:
        return ros_or_refused(exc)
    try:
        try:
            K = storage.getNode("camera_matrix").mat()
        except cv2.error as exc:  # OpenCV 5 opens a file without the header, and fails on its first node instead
            return ros_or_refused(exc)
        if K is None:
            raise CameraFileError(f"{path} has no camera_matrix (an opencv-matrix node)")
        dist = storage.getNode("distortion_coefficients").mat()
        size, model = _size_and_model(storage, path)
    finally:
        storage.release()
    return _camera(path, K, dist, size, model)


def _size_and_model(storage: cv2.FileStorage, path: Path) -> tuple[tuple[int, int], str]:
    """A camera file's (image_width, image_height) and its ``distortion_model`` as written ("pinhole" when absent);
    `CameraFileError` where the size is missing. OpenCV's layout and ROS's name these nodes alike."""
    width_node, height_node = storage.getNode("image_width"), storage.getNode("image_height")
    if width_node.empty() or height_node.empty():
        raise CameraFileError(f"{path} lacks image_width / image_height: add the calibration resolution")
    model_node = storage.getNode("distortion_model")
    return (int(width_node.real()), int(height_node.real())), "pinhole" if model_node.empty() else model_node.string()


def _camera(path: Path, K: np.ndarray, dist: np.ndarray | None, size: tuple[int, int], model: str) -> Camera:
    """The `Camera` a file's nodes describe; ``model`` as the file names it."""
    # "rational" (deepcharuco.cli.calibrate's name for the 8-coefficient model) and the names OpenCV's samples and
    # ROS write for the standard model are all the one cv2.projectPoints applies.
    model = "pinhole" if model in ("pinhole", "rational", "plumb_bob", "rational_polynomial") else model
    if model == "equidistant":
        model = "fisheye"
    if model not in CAMERA_MODELS:
        raise CameraFileError(f"{path}: distortion_model {model!r} is not one OpenCV applies; use pinhole, rational "
                              f"or fisheye")
    return Camera(K=K, dist=np.zeros(4 if model == "fisheye" else 5) if dist is None else dist, image_size=size,
                  model=model)


ROS_MAX_BYTES = 64 * 1024  # a camera_info YAML is well under 2 KiB


def _ros_camera_info(path: Path) -> Camera | None:
    """The camera of a ROS ``camera_info`` YAML (camera_calibration_parsers' layout, as ``calibrate --export ros``
    writes it: ``camera_matrix`` and ``distortion_coefficients`` as ``{rows, cols, data}``, ``distortion_model``
    plumb_bob, rational_polynomial or equidistant), read by OpenCV's parser with the header such files lack; None
    where the file is not one. K and D are the raw camera's: right for the images the camera recorded."""
    try:
        if path.stat().st_size > ROS_MAX_BYTES:
            return None
        text = path.read_text()
        storage = cv2.FileStorage("%YAML:1.0\n" + text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except (OSError, UnicodeDecodeError, cv2.error, SystemError):
        return None
    try:
        values = _ros_matrix(storage.getNode("camera_matrix"))
        if values is None:
            return None
        if len(values) != 9:
            raise CameraFileError(f"{path}: a ROS camera_info file whose camera_matrix holds {len(values)} values, "
                                  f"not 9")
        dist = _ros_matrix(storage.getNode("distortion_coefficients"))
        size, model = _size_and_model(storage, path)
    finally:
        storage.release()
    return _camera(path, values.reshape(3, 3), dist, size, model)


def _ros_matrix(node: cv2.FileNode) -> np.ndarray | None:
    """A ROS matrix node's ``data`` ({rows, cols, data}) as a flat float64 array, or None where it is not one."""
    if not node.isMap() or not node.getNode("data").isSeq():
        return None
    data = node.getNode("data")
    return np.array([data.at(i).real() for i in range(data.size())], np.float64)


def write_camera(path: str | Path, camera: Camera,
                 extra: Callable[[cv2.FileStorage], None] | None = None) -> Path:
    """Write intrinsics in OpenCV's FileStorage format (YAML unless the suffix says .xml/.json); a fisheye
    camera's file says so in ``distortion_model`` (else its 4 coefficients read as k1 k2 p1 p2). ``extra``
    writes further nodes after these. The file is composed in memory and written by
    `deepcharuco.core.files.write_atomic`: a failed write (a full disk) raises and leaves an existing file as it was."""
    path = Path(path)
    return write_atomic(path, camera_file_text(camera, path.name, extra))


def camera_file_text(camera: Camera, name: str = "camera.yaml",
                     extra: Callable[[cv2.FileStorage], None] | None = None) -> str:
    """The text of `write_camera`'s file named ``name`` (its suffix picks YAML, XML or JSON)."""
    # OpenCV's FileStorage does not report failed writes; in memory it cannot fail half-way.
    storage = cv2.FileStorage(name, cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    storage.write("image_width", camera.image_size[0])
    storage.write("image_height", camera.image_size[1])
    storage.write("camera_matrix", camera.K)
    storage.write("distortion_coefficients", camera.dist.reshape(-1, 1))
    if camera.model != "pinhole":
        storage.write("distortion_model", camera.model)
    if extra is not None:
        extra(storage)
    return storage.releaseAndGetString()


def is_camera_file(path: str | Path) -> bool:
    """True when ``path`` reads as a camera file (`read_camera`): what a command may overwrite."""
    try:
        read_camera(path)
    except (CameraFileError, cv2.error, SystemError):
        return False
    return True
