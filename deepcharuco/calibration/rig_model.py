"""A rig's data: `RigView` (one camera's corners of one board at one instant), `RigResult` (the solved rig, its
deviations and what was dropped, `Dropped`), `RigError`, and the small rigid-motion helpers every step of the rig's
solve shares (poses as (R, t) with x_cam = R X + t, metres; OpenCV's pinhole, rational and fisheye projection).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from deepcharuco.calibration.views import CalibrationError, checked_covariances
from deepcharuco.geometry.camera import Camera


# Intrinsic parameters of a camera in the bundle adjustment, in this order (OpenCV's pinhole and rational models).
# A fisheye camera (cv2.fisheye's k1..k4) keeps its terms in the slots of their names, p1 p2 k5 k6 unused.
INTRINSICS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
FISHEYE_TERMS = ("k1", "k2", "k3", "k4")


class RigError(CalibrationError):
    """Views that cannot give a rig; the message says what to capture or give instead."""


@dataclass
class RigView:
    """One camera's detection of one board at one instant: ``ids`` (N,) int64, ``corners`` (N, 2) float64 pixels,
    ``name`` the frame's name in its source, ``board`` the board's index (several boards: `calibrate_rig`),
    ``covariances`` (N, 2, 2) px^2 each corner's covariance from its detector (`Detection.covariances`; None: not
    given, and the corners weigh alike)."""

    camera: int
    instant: int
    ids: np.ndarray
    corners: np.ndarray
    name: str = ""
    board: int = 0
    covariances: np.ndarray | None = None

    @property
    def key(self) -> tuple[int, int]:
        """(instant, board): what one board pose is solved for."""
        return self.instant, self.board

    def __post_init__(self) -> None:
        self.ids = np.asarray(self.ids, np.int64).reshape(-1)
        self.corners = np.asarray(self.corners, np.float64).reshape(-1, 2)
        self.covariances = checked_covariances(self.covariances)

    def subset(self, keep: np.ndarray) -> "RigView":
        """The view with only the corners ``keep`` (a boolean mask or indices) selects."""
        covariances = None if self.covariances is None else self.covariances[keep]
        return RigView(self.camera, self.instant, self.ids[keep], self.corners[keep], self.name, self.board, covariances)


@dataclass
class Dropped:
    """A view left out and why: stage "detection" | "pose" | "outlier"."""

    camera: int
    instant: int
    name: str
    corners: int
    stage: str
    reason: str
    board: int = 0

    def to_dict(self) -> dict:
        return {"camera": self.camera, "instant": self.instant, "board": self.board, "name": self.name,
                "corners": self.corners, "stage": self.stage, "reason": self.reason}


@dataclass
class RigResult:
    """A solved rig.

    Attributes:
        cameras: each camera's intrinsics; names: their names (video stems).
        rotations: (C, 3, 3) and translations: (C, 3) metres: x_cam = R X + t, X in the rig's frame (camera 0's).
        board_poses: {(instant, board): (rvec (3,), tvec (3,))} each board -> the rig's frame at each instant used.
        views: the views used (their corners after outlier rejection); residuals: per view (N_v, 2) detected
            minus reprojected pixels.
        std: per camera {name: standard deviation}: the free intrinsics (px, unitless distortion) and the pose's
            "rotation_deg" (the rotation vector's largest axis deviation, degrees) and "tx" "ty" "tz" (metres).
        shared: {(i, j): instants both cameras i < j saw one board at (counted once per board), among the views used}.
        dropped: the views left out and why; notes: what the user should know; terms: per camera the distortion
            terms solved ("" when its intrinsics were held fixed).
    """

    cameras: list[Camera]
    names: list[str]
    rotations: np.ndarray
    translations: np.ndarray
    board_poses: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]]
    views: list[RigView]
    residuals: list[np.ndarray]
    std: list[dict[str, float]]
    shared: dict[tuple[int, int], int]
    dropped: list[Dropped]
    notes: list[str] = field(default_factory=list)
    terms: list[str] = field(default_factory=list)
    rounds: int = 1
    # the cameras' disagreement: the rig's corner noise (intrinsics held) over the cameras' own (`MAX_DISAGREEMENT`)
    disagreement: float = math.nan
    corners_weighed: bool = False  # each corner weighed by its detector's covariance and its view's excess

    def camera_rms(self, camera: int) -> float:
        """RMS reprojection error (px, per corner) of ``camera``'s views used."""
        r = [res for v, res in zip(self.views, self.residuals) if v.camera == camera]
        if not r:
            return math.nan
        stacked = np.concatenate(r)
        return float(np.sqrt(np.mean(np.sum(stacked ** 2, axis=1))))

    @property
    def rms(self) -> float:
        stacked = np.concatenate(self.residuals)
        return float(np.sqrt(np.mean(np.sum(stacked ** 2, axis=1))))

    def camera_views(self, camera: int) -> int:
        return sum(v.camera == camera for v in self.views)

    def centre(self, camera: int) -> np.ndarray:
        """(3,) the camera's centre in the rig's frame (metres)."""
        return -self.rotations[camera].T @ self.translations[camera]

    def reframed(self, rotation: np.ndarray, translation: np.ndarray) -> "RigResult":
        """The same rig in another frame: X_rig = rotation @ X_new + translation (e.g. the board's at an instant)."""
        rotations = self.rotations @ rotation
        translations = np.einsum("cij,j->ci", self.rotations, translation) + self.translations
        inverse_r, inverse_t = rotation.T, -rotation.T @ translation
        poses = {}
        for key, (rvec, tvec) in self.board_poses.items():
            R = cv2.Rodrigues(rvec)[0]
            poses[key] = (cv2.Rodrigues(inverse_r @ R)[0].ravel(), inverse_r @ tvec + inverse_t)
        return RigResult(self.cameras, self.names, rotations, translations, poses, self.views, self.residuals,
                         self.std, self.shared, self.dropped, list(self.notes), list(self.terms), self.rounds,
                         self.disagreement, self.corners_weighed)

    def summary(self) -> dict:
        """JSON-ready numbers: per camera its intrinsics, pose, RMS, views and deviations; pairs; drops."""
        cameras = []
        for c, camera in enumerate(self.cameras):
            K = camera.K
            cameras.append({"name": self.names[c], "image_size": list(camera.image_size), "fx": K[0, 0], "fy": K[1, 1],
                            "cx": K[0, 2], "cy": K[1, 2], "dist": camera.dist.tolist(),
                            "rotation_matrix": self.rotations[c].tolist(), "translation_m": self.translations[c].tolist(),
                            "centre_m": self.centre(c).tolist(), "rms_px": self.camera_rms(c),
                            "views": self.camera_views(c), "std": self.std[c],
                            "terms": self.terms[c] if c < len(self.terms) else ""})
        return {"cameras": cameras, "rms_px": self.rms, "instants": len({i for i, _ in self.board_poses}),
                "board_poses": len(self.board_poses),
                "shared_views": {f"{self.names[i]}-{self.names[j]}": n for (i, j), n in sorted(self.shared.items())},
                "dropped": [d.to_dict() for d in self.dropped], "notes": self.notes, "rounds": self.rounds,
                "disagreement": self.disagreement, "corners_weighed": self.corners_weighed}


# ----------------------------------------------------------------------------------------- geometry
def cross_matrices(v: np.ndarray) -> np.ndarray:
    """(K, 3) vectors -> (K, 3, 3) their cross-product matrices [v]x."""
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    zero = np.zeros_like(x)
    return np.stack([np.stack([zero, -z, y], 1), np.stack([z, zero, -x], 1), np.stack([-y, x, zero], 1)], 1)


def rotations_from_vectors(rvecs: np.ndarray) -> np.ndarray:
    """(K, 3, 3) rotation matrices of the (K, 3) rotation vectors (Rodrigues' formula, exact near 0)."""
    rvecs = np.asarray(rvecs, np.float64).reshape(-1, 3)
    theta = np.linalg.norm(rvecs, axis=1)
    small = theta < 1e-12
    axis = rvecs / np.where(small, 1.0, theta)[:, None]
    cross = cross_matrices(axis)
    sin, cos = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    outer = axis[:, :, None] * axis[:, None, :]
    rotation = cos * np.eye(3) + sin * cross + (1 - cos) * outer
    rotation[small] = np.eye(3)
    return rotation


def project(points_cam: np.ndarray, intrinsics: np.ndarray, fisheye: np.ndarray | None = None) -> np.ndarray:
    """(M, 2) pixels of the (M, 3) camera-frame points, each through its own (M, 12) intrinsics (`INTRINSICS`
    order): OpenCV's pinhole model, ``cv2.projectPoints``' formula; where ``fisheye`` (M,) bool is set, OpenCV's
    fisheye model instead (`project_fisheye`)."""
    fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6 = intrinsics.T
    z = points_cam[:, 2]
    x, y = points_cam[:, 0] / z, points_cam[:, 1] / z
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    pixels = np.column_stack([fx * xd + cx, fy * yd + cy])
    if fisheye is not None and fisheye.any():
        pixels[fisheye] = project_fisheye(points_cam[fisheye], intrinsics[fisheye])
    return pixels


def project_fisheye(points_cam: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """(M, 2) pixels of the (M, 3) camera-frame points through OpenCV's fisheye (equidistant) model, k1..k4 in the
    (M, 12) intrinsics' `FISHEYE_TERMS` slots: ``cv2.fisheye.projectPoints``' formula (no skew), theta_d = theta (1 +
    k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8) with theta the ray's angle off the axis. theta is taken as
    atan2(rho, z): the same as OpenCV's atan(rho / z) in front of the camera, and steady where z nears 0 (a ray 90
    degrees off the axis, which a 180 degree lens sees)."""
    fx, fy, cx, cy, k1, k2, _, _, k3, k4, _, _ = intrinsics.T
    rho = np.hypot(points_cam[:, 0], points_cam[:, 1])
    theta = np.arctan2(rho, points_cam[:, 2])
    t2 = theta * theta
    theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    # OpenCV's x * theta_d / r with x = X / z, r = rho / z: X theta_d / rho, and 1 on the axis
    on_axis = rho < 1e-8 * np.abs(points_cam[:, 2])
    scale = np.where(on_axis, 1.0 / np.where(points_cam[:, 2] == 0, 1.0, points_cam[:, 2]),
                     theta_d / np.where(on_axis, 1.0, rho))
    return np.column_stack([fx * points_cam[:, 0] * scale + cx, fy * points_cam[:, 1] * scale + cy])


def distortion_names(camera: Camera) -> tuple[str, ...]:
    """The names of ``camera.dist``'s coefficients, in its order (`INTRINSICS`' names)."""
    if camera.model == "fisheye":
        return FISHEYE_TERMS
    return ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")[:camera.dist.size]


def intrinsic_vector(camera: Camera) -> np.ndarray:
    """(12,) the camera's parameters in `INTRINSICS` order (absent distortion terms are 0)."""
    K = camera.K
    vector = np.zeros(12)
    vector[:4] = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    for name, value in zip(distortion_names(camera), camera.dist[:8]):
        vector[INTRINSICS.index(name)] = value
    return vector


def camera_from_vector(vector: np.ndarray, image_size: tuple[int, int], terms: int, model: str = "pinhole") -> Camera:
    """The `Camera` of a (12,) `INTRINSICS` vector with ``terms`` distortion coefficients (5 or 8; a fisheye
    ``model``'s: its 4)."""
    fx, fy, cx, cy = vector[:4]
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    if model == "fisheye":
        return Camera(K=K, dist=vector[[INTRINSICS.index(name) for name in FISHEYE_TERMS]].copy(),
                      image_size=image_size, model="fisheye")
    return Camera(K=K, dist=vector[4:4 + terms].copy(), image_size=image_size)


def compose(R_a: np.ndarray, t_a: np.ndarray, R_b: np.ndarray, t_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The transform x -> a(b(x)) of two (R, t) transforms x -> R x + t."""
    return R_a @ R_b, R_a @ t_b + t_a


def invert(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return R.T, -R.T @ t


def rotation_angle_deg(R: np.ndarray) -> float:
    """The angle (degrees) of the rotation matrix ``R``."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))
