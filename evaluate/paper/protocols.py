"""The paper's evaluation protocols (docs/conventions.md), each usable on its own with any detector.

A detector is anything with the runtime API's interface (docs/conventions.md): ``detect(gray_u8) -> Detection`` and
``estimate_pose(detection, K, dist) -> Pose | None`` (`deepcharuco.Detector`,
`deepcharuco.OpenCVDetector`). A test frame is a `TestFrame`: an image with its true corners.

- corner detection accuracy: a corner is correct when its ID is right and it lies < 3 px
  from the truth; accuracy = correct / all board corners, averaged over images
  (`deepcharuco.detection.metrics.match_corners`); plus the sub-pixel error of the correct ones;
- synthetic motion blur: horizontal box kernel of size k = 0..10 (`motion_blur`);
- synthetic darkness: image x 0.6^k, k = 0..10 (`darken`);
- pose: solvePnPRansac with the known K; eps_re = mean reprojection error of the detected
  corners; a frame is correct when eps_re < 3 px; accuracy vs threshold 0..10 px; and,
  against the true pose, rotation / translation error and **confidently wrong** poses;
- timing: frames per second of whole pipelines (detect + pose) on the same images, interleaved
  in one run so that every configuration sees the same machine load.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Iterable, Protocol

import cv2
import numpy as np

from deepcharuco.core.detection import Detection
from deepcharuco.detection.metrics import CORRECT_RADIUS_PX, match_corners
from deepcharuco.geometry.pose import Pose

LEVELS = tuple(range(11))  # k = 0..10 for both synthetic protocols
DARKNESS_BASE = 0.6
POSE_THRESHOLD_PX = 3.0
THRESHOLDS_PX = tuple(np.round(np.linspace(0.0, 10.0, 101), 2))
# A returned pose this far from the truth is "confidently wrong": the detector gave an answer
# a user would act on, and it is not the board's pose.
WRONG_ROTATION_DEG = 10.0
WRONG_TRANSLATION_FRACTION = 0.10


class DetectorLike(Protocol):
    def detect(self, image: np.ndarray) -> Detection: ...

    def estimate_pose(self, detection: Detection, K: np.ndarray, dist: np.ndarray | None = None) -> Pose | None: ...


@dataclass
class TestFrame:
    """One evaluation image and its truth.

    Attributes:
        image: (H, W) uint8 grayscale.
        corners: (C, 2) float32 true corner positions (OpenCV pixels), NaN where unknown.
        visible: (C,) bool: corners that can be seen (a detection of another counts as wrong).
        K: (3, 3) camera matrix; rvec, tvec: (3,) true board -> camera pose (None: unknown).
        name: where it comes from ("shard-00003.h5#17"); meta: the shard's per-frame meta.
    """

    __test__ = False  # not a pytest class, despite the name

    image: np.ndarray
    corners: np.ndarray
    visible: np.ndarray
    K: np.ndarray
    rvec: np.ndarray | None = None
    tvec: np.ndarray | None = None
    name: str = ""
    meta: dict = field(default_factory=dict)


# --- synthetic effects -------------------------------------------------------------------------

def motion_blur(image: np.ndarray, k: int) -> tuple[np.ndarray, float]:
    """Horizontal box blur of ``k`` pixels (k <= 1: unchanged) -> (image, x shift of the content in px).

    OpenCV anchors an even-length kernel at its ``k // 2``-th tap, which moves the image content
    by +0.5 px in x; the shift is returned so the truth can move with it (the 3 px rule would
    hide it, the sub-pixel error would not)."""
    if k <= 1:
        return image.copy(), 0.0
    kernel = np.full((1, k), 1.0 / k, dtype=np.float32)
    blurred = cv2.filter2D(image.astype(np.float32), -1, kernel, borderType=cv2.BORDER_REFLECT)
    return np.clip(np.rint(blurred), 0, 255).astype(np.uint8), (k // 2) - (k - 1) / 2.0


def darken(image: np.ndarray, k: int, base: float = DARKNESS_BASE) -> np.ndarray:
    """``image`` x base^k, rounded to 8 bits (k = 9 leaves ~1 % of the light: a 255 white becomes 3)."""
    return np.clip(np.rint(image.astype(np.float32) * base ** k), 0, 255).astype(np.uint8)


def apply_effect(frame: TestFrame, effect: str, k: int) -> TestFrame:
    """``frame`` with the synthetic ``effect`` ("blur" or "darkness") of strength ``k``; truth moved with it."""
    if effect == "blur":
        image, shift = motion_blur(frame.image, k)
        corners = frame.corners + np.array([shift, 0.0], np.float32)
    elif effect == "darkness":
        image, corners = darken(frame.image, k), frame.corners
    else:
        raise ValueError(f"effect must be 'blur' or 'darkness', got {effect!r}")
    return TestFrame(image, corners, frame.visible, frame.K, frame.rvec, frame.tvec, f"{frame.name} {effect} k={k}",
                     frame.meta)


# --- corner accuracy ---------------------------------------------------------------------------

@dataclass
class CornerScore:
    """One detection scored against one frame's truth."""

    accuracy: float  # correct / all board corners
    num_detected: int
    num_correct: int
    subpixel_errors: np.ndarray  # (num_correct,) px


def score_corners(detection: Detection, frame: TestFrame, radius: float = CORRECT_RADIUS_PX) -> CornerScore:
    match = match_corners(detection, frame.corners, frame.visible, radius)
    return CornerScore(match.accuracy, len(detection), match.num_correct, match.subpixel_errors)


@dataclass
class SyntheticCurve:
    """Accuracy of one detector under one synthetic effect, per level k.

    Attributes:
        effect: "blur" or "darkness"; levels: the k values.
        accuracy: (L,) mean corner accuracy over the frames at each level.
        per_frame: (L, F) the accuracy of each frame at each level.
        subpixel_error: (L,) mean distance (px) of the correct corners (NaN when none).
    """

    effect: str
    levels: tuple[int, ...]
    accuracy: np.ndarray
    per_frame: np.ndarray
    subpixel_error: np.ndarray
    detections: list[list[Detection]] = field(repr=False, default_factory=list)  # [level][frame]

    def to_dict(self) -> dict:
        return {"effect": self.effect, "levels": list(self.levels), "accuracy": _floats(self.accuracy),
                "subpixel_error_px": _floats(self.subpixel_error), "per_frame": [_floats(r) for r in self.per_frame]}


def synthetic_curve(detector: DetectorLike, frames: list[TestFrame], effect: str, levels: Iterable[int] = LEVELS,
                    progress: Callable[[], None] | None = None) -> SyntheticCurve:
    """The paper's synthetic motion-blur or darkness test: every frame at every level."""
    levels = tuple(levels)
    per_frame = np.zeros((len(levels), len(frames)))
    errors: list[list[np.ndarray]] = [[] for _ in levels]
    detections: list[list[Detection]] = [[] for _ in levels]
    for i, k in enumerate(levels):
        for j, frame in enumerate(frames):
            altered = apply_effect(frame, effect, k)
            detection = detector.detect(altered.image)
            score = score_corners(detection, altered)
            per_frame[i, j] = score.accuracy
            errors[i].append(score.subpixel_errors)
            detections[i].append(detection)
            if progress:
                progress()
    subpixel = np.array([np.concatenate(e).mean() if sum(map(len, e)) else np.nan for e in errors])
    return SyntheticCurve(effect, levels, per_frame.mean(axis=1) if frames else np.zeros(len(levels)), per_frame,
                          subpixel, detections)


# --- pose --------------------------------------------------------------------------------------

def rotation_error_deg(rvec_a: np.ndarray, rvec_b: np.ndarray) -> float:
    """Angle (degrees) of the rotation between two Rodrigues vectors."""
    ra, _ = cv2.Rodrigues(np.asarray(rvec_a, np.float64).reshape(3, 1))
    rb, _ = cv2.Rodrigues(np.asarray(rvec_b, np.float64).reshape(3, 1))
    return float(np.degrees(np.arccos(np.clip((np.trace(ra.T @ rb) - 1.0) / 2.0, -1.0, 1.0))))


@dataclass
class PoseScore:
    """One frame through detection + pose.

    eps_re is inf when no pose was returned; rotation_deg / translation_fraction are NaN when no
    pose or no true pose. ``confidently_wrong``: a pose was returned and it is more than 10 degrees
    or 10 % of the distance from the truth."""

    name: str
    accuracy: float
    num_detected: int
    eps_re: float
    rotation_deg: float
    translation_fraction: float
    confidently_wrong: bool
    detection: Detection = field(repr=False, default=None)

    @property
    def has_pose(self) -> bool:
        return bool(np.isfinite(self.eps_re))

    def to_dict(self) -> dict:
        return {"name": self.name, "accuracy": self.accuracy, "num_detected": self.num_detected,
                "eps_re": _float(self.eps_re), "rotation_deg": _float(self.rotation_deg),
                "translation_fraction": _float(self.translation_fraction), "confidently_wrong": self.confidently_wrong}


def score_pose(detector: DetectorLike, frame: TestFrame) -> PoseScore:
    """Detect, estimate the pose with the frame's K, and compare both with the truth."""
    detection = detector.detect(frame.image)
    corners = score_corners(detection, frame)
    pose = detector.estimate_pose(detection, frame.K, None)
    eps, rotation, translation, wrong = np.inf, np.nan, np.nan, False
    if pose is not None:
        eps = pose.reprojection_error
        if frame.rvec is not None and frame.tvec is not None and np.all(np.isfinite(frame.tvec)):
            rotation = rotation_error_deg(pose.rvec, frame.rvec)
            distance = float(np.linalg.norm(frame.tvec))
            translation = float(np.linalg.norm(pose.tvec - frame.tvec)) / max(distance, 1e-9)
            wrong = rotation > WRONG_ROTATION_DEG or translation > WRONG_TRANSLATION_FRACTION
    return PoseScore(frame.name, corners.accuracy, len(detection), float(eps), rotation, translation, wrong, detection)


def accuracy_vs_threshold(eps_re: np.ndarray, thresholds: Iterable[float] = THRESHOLDS_PX) -> np.ndarray:
    """Fraction of frames whose eps_re is below each threshold; frames without a pose (inf) never are."""
    eps_re = np.asarray(eps_re, dtype=np.float64)
    if eps_re.size == 0:
        return np.zeros(len(tuple(thresholds)))
    return np.array([(eps_re < t).mean() for t in thresholds])


@dataclass
class PoseSummary:
    """The paper's per-sequence numbers for one detector over a set of frames."""

    frames: int
    pose_accuracy: float  # fraction with eps_re < 3 px (the paper's "acc")
    mean_eps_re: float  # over the frames with a pose (NaN if none: the paper's "nan")
    found: float  # fraction of frames with any pose
    corner_accuracy: float  # mean corner accuracy
    confidently_wrong: int
    median_rotation_deg: float
    median_translation_fraction: float

    def to_dict(self) -> dict:
        return {k: _float(v) if isinstance(v, float) else v for k, v in self.__dict__.items()}


def summarize_poses(scores: list[PoseScore], threshold: float = POSE_THRESHOLD_PX) -> PoseSummary:
    eps = np.array([s.eps_re for s in scores], dtype=np.float64)
    posed = np.isfinite(eps)
    rotation = np.array([s.rotation_deg for s in scores], dtype=np.float64)
    translation = np.array([s.translation_fraction for s in scores], dtype=np.float64)
    return PoseSummary(
        frames=len(scores),
        pose_accuracy=float((eps < threshold).mean()) if len(scores) else 0.0,
        mean_eps_re=float(eps[posed].mean()) if posed.any() else float("nan"),
        found=float(posed.mean()) if len(scores) else 0.0,
        corner_accuracy=float(np.mean([s.accuracy for s in scores])) if scores else 0.0,
        confidently_wrong=int(sum(s.confidently_wrong for s in scores)),
        median_rotation_deg=float(np.nanmedian(rotation)) if np.isfinite(rotation).any() else float("nan"),
        median_translation_fraction=float(np.nanmedian(translation)) if np.isfinite(translation).any() else float("nan"),
    )


# --- timing ------------------------------------------------------------------------------------

def time_pipelines(pipelines: dict[str, DetectorLike], frames: list[TestFrame], rounds: int = 3,
                   min_seconds: float = 1.0) -> dict[str, float]:
    """Frames per second of detect + estimate_pose for each named pipeline, on the same frames.

    Rounds interleave the pipelines (A B C A B C ...) so that load changes on the machine hit
    all of them alike; each pipeline's time is the median over rounds of one pass over the
    frames (repeated until ``min_seconds``). One untimed warm-up pass each first."""
    if not frames:
        raise ValueError("timing needs at least one frame")

    def one_pass(detector: DetectorLike) -> None:
        for frame in frames:
            detector.estimate_pose(detector.detect(frame.image), frame.K, None)

    for detector in pipelines.values():
        one_pass(detector)
    seconds_per_frame: dict[str, list[float]] = {name: [] for name in pipelines}
    for _ in range(rounds):
        for name, detector in pipelines.items():
            passes, started = 0, time.perf_counter()
            while True:
                one_pass(detector)
                passes += 1
                elapsed = time.perf_counter() - started
                if elapsed >= min_seconds / rounds:
                    break
            seconds_per_frame[name].append(elapsed / (passes * len(frames)))
    return {name: 1.0 / float(np.median(times)) for name, times in seconds_per_frame.items()}


def _float(value) -> float | None:
    value = float(value)
    return value if np.isfinite(value) else None  # JSON has no NaN / inf


def _floats(values) -> list[float | None]:
    return [_float(v) for v in np.asarray(values).ravel()]
