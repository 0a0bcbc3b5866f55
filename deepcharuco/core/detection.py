"""`Detection`: the one result type every detector returns."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from deepcharuco.core.errors import OptionError, ShapeError
from deepcharuco.core.vectors import pairwise_distances


def largest_sigmas(covariances: np.ndarray) -> np.ndarray:
    """(N, 2, 2) covariances (px^2) -> (N,) float32 px: each one's standard deviation along its least certain
    direction (the square root of the larger eigenvalue); NaN where a covariance is not finite."""
    covariances = np.asarray(covariances, np.float64).reshape(-1, 2, 2)
    finite = np.all(np.isfinite(covariances), axis=(1, 2))
    largest = np.full(len(covariances), np.nan)
    if finite.any():
        largest[finite] = np.linalg.eigvalsh(covariances[finite])[:, -1]
    return np.sqrt(np.maximum(largest, 0.0)).astype(np.float32)


def no_corners() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ids (0,) int64, corners (0, 2) float32, scores (0,) float32): the decoders' answer when nothing is found."""
    return np.zeros(0, np.int64), np.zeros((0, 2), np.float32), np.zeros(0, np.float32)


@dataclass(frozen=True)
class Detection:
    """Board corners found in one image.

    Attributes:
        ids: (N,) int64 unique corner IDs (OpenCV's ChArUco IDs), ascending.
        corners: (N, 2) float32 pixel positions; the centre of the top-left pixel is (0, 0).
        scores: (N,) float32 confidences in [0, 1].
        covariances: (N, 2, 2) float32 each corner's position covariance (px^2, x then y) about the true corner,
            calibrated on validation views (docs/detector.md); NaN where the detector gives none (None: all NaN).
    """

    ids: np.ndarray
    corners: np.ndarray
    scores: np.ndarray
    covariances: np.ndarray | None = None

    def __post_init__(self) -> None:
        ids = np.asarray(self.ids, dtype=np.int64).reshape(-1)
        corners = np.asarray(self.corners, dtype=np.float32).reshape(-1, 2)
        scores = np.asarray(self.scores, dtype=np.float32).reshape(-1)
        covariances = np.full((len(ids), 2, 2), np.nan, np.float32) if self.covariances is None else \
            np.asarray(self.covariances, dtype=np.float32).reshape(-1, 2, 2)
        if not (ids.shape[0] == corners.shape[0] == scores.shape[0] == covariances.shape[0]):
            raise ShapeError(f"ids, corners, scores and covariances disagree in length: {ids.shape[0]}, "
                             f"{corners.shape[0]}, {scores.shape[0]}, {covariances.shape[0]}")
        if np.unique(ids).size != ids.size:
            raise OptionError(f"corner IDs must be unique, got {ids.tolist()}")
        order = np.argsort(ids, kind="stable")
        object.__setattr__(self, "ids", ids[order])
        object.__setattr__(self, "corners", corners[order])
        object.__setattr__(self, "scores", scores[order])
        object.__setattr__(self, "covariances", covariances[order])

    @property
    def sigmas(self) -> np.ndarray:
        """(N,) float32 px: `largest_sigmas` of the corners' covariances."""
        return largest_sigmas(self.covariances)

    def information(self) -> np.ndarray | None:
        """(N, 2, 2) float64 inverse covariances (px^-2), the weights of a least-squares fit of these corners, or None
        where any corner has no covariance."""
        if len(self) == 0 or not np.all(np.isfinite(self.covariances)):
            return None
        return np.linalg.inv(self.covariances.astype(np.float64))

    @classmethod
    def empty(cls) -> "Detection":
        return cls(*no_corners())

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def to_dict(self) -> dict:
        return {
            "ids": self.ids.tolist(),
            "corners": self.corners.astype(float).round(4).tolist(),
            "scores": self.scores.astype(float).round(4).tolist(),
            # (xx, xy, yy) px^2 per corner; null where the detector gives none (JSON has no NaN)
            "covariances": [[round(float(c[0, 0]), 6), round(float(c[0, 1]), 6), round(float(c[1, 1]), 6)]
                            if np.all(np.isfinite(c)) else None for c in self.covariances],
        }


# What ``cv2.aruco.CharucoDetector.detectBoard`` returns: (charuco corners (N, 1, 2) float32 or None, charuco ids
# (N, 1) int32 or None, marker corners: a tuple of (1, 4, 2) float32, marker ids (M, 1) int32 or None).
OpenCVBoardResult = tuple


def detect_board_result(detection: "Detection", marker_corners: tuple = (), marker_ids: np.ndarray | None = None
                        ) -> OpenCVBoardResult:
    """``detection`` in the shapes and types ``cv2.aruco.CharucoDetector.detectBoard`` returns (None for the
    corners and ids when there are none, as OpenCV), so a script written for OpenCV's call takes it unchanged."""
    if len(detection) == 0:
        return None, None, tuple(marker_corners), marker_ids
    return (detection.corners.reshape(-1, 1, 2).astype(np.float32), detection.ids.reshape(-1, 1).astype(np.int32),
            tuple(marker_corners), marker_ids)


def corner_spacing(corners: np.ndarray) -> float:
    """Median distance from each of (N, 2) corners to its nearest other corner (~ the square side), pixels;
    0 for fewer than 2."""
    if len(corners) < 2:
        return 0.0
    distance = pairwise_distances(corners.astype(np.float64), corners)
    np.fill_diagonal(distance, np.inf)
    return float(np.median(distance.min(axis=1)))
