"""What a calibration keeps of each frame, and which frames become its views (steps 0-2 of `intrinsics`).

`FrameDetection` is one frame's corners (never its image); `within_border` drops corners too near the border for
their refiner, `usable_reason` says why a frame cannot be a view, and `select_views` picks views that cover the
image and the board's tilts (farthest-point sampling over `view_features`), dropping blurred frames and
near-duplicates. `coverage` measures how much of the image the kept corners reach. `CalibrationError` (one line
saying what to capture instead) is raised here and in every later step.

Pixels: OpenCV's convention (centre of the top-left pixel at (0, 0)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.geometry.pose import MIN_SPREAD_RATIO


MIN_COVERAGE = 0.5  # below this share of the image holding corners, the result says the distortion is extrapolated
MIN_TILT_SPREAD_DEG = 10.0  # Zhang's method needs at least two board orientations this far apart


# `weigh_views`: motion blur smears a view's corners along the blur, by up to a few px in a shaken video, while in
# good light every view is alike (0.1 px); OpenCV weighs every corner alike, so 1-2 px views count as much as
# 0.1 px ones. A view whose residuals spread (per axis, in their widest direction) by more than this x the median
# view's counts less in that direction, in proportion to its variance there; the others keep their full weight.
# Chosen on validation shake videos only (seed 0, and seeds 3 and 4 rendered for it; 9 videos, the deep detector of
# e39f0bd): worst fx/fy error 0.62 -> 0.56 %, mean 0.28 -> 0.27 % (better on 5, worse on 4: seed 0's k1 +0.10 by
# 0.30 %), mean worst |cx|, |cy| 1.07 -> 0.71 px; good light and 1 lux (seed 0) moved <= 0.04 % and 0.11 px.
# At 1.0 seed 0's k1 -0.15 good-light cy reached -1.02 px (past the 1 px target); 1.25 was as good under shake and
# nearer that edge (-0.99 px); 2.0 gave the same fx/fy and less of the principal point (0.78 px).
VIEW_WEIGHT_SPREAD = 1.5


class CalibrationError(DeepCharucoError):
    """Frames that cannot give a calibration; the message says what to capture instead."""


def checked_covariances(covariances) -> np.ndarray | None:
    """Corners' covariances as (N, 2, 2) float64 px^2, or None where none are given or any is not finite: a weight
    for some corners only would weigh the others by nothing."""
    if covariances is None:
        return None
    covariances = np.asarray(covariances, np.float64).reshape(-1, 2, 2)
    return covariances if np.all(np.isfinite(covariances)) else None


@dataclass
class FrameDetection:
    """What calibration keeps of one frame (never the image).

    Attributes:
        index: frame number in the source; name: its name (file name or frame number).
        ids: (N,) int64 corner IDs; corners: (N, 2) float64 pixels.
        sharpness: `sharpness` of the frame around the board (0 without corners).
        covariances: (N, 2, 2) each corner's covariance (px^2, `Detection.covariances`); None where the detector
            gives none.
    """

    index: int
    name: str
    ids: np.ndarray
    corners: np.ndarray
    sharpness: float = 0.0
    covariances: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.ids = np.asarray(self.ids, np.int64).reshape(-1)
        self.corners = np.asarray(self.corners, np.float64).reshape(-1, 2)
        self.covariances = checked_covariances(self.covariances)

    def subset(self, keep: np.ndarray) -> "FrameDetection":
        """This frame with only its corners ``keep`` (a bool mask or indices)."""
        covariances = None if self.covariances is None else self.covariances[keep]
        return FrameDetection(self.index, self.name, self.ids[keep], self.corners[keep], self.sharpness, covariances)


@dataclass
class ViewDecision:
    """Why a frame was used or not: ``status`` "kept" | "dropped"; ``stage`` where it was decided
    ("detection", "selection", "outlier", "solution"); ``reason`` in words; ``rms`` its error (px) in
    the final solution when kept or dropped as an outlier."""

    index: int
    name: str
    corners: int
    status: str
    stage: str
    reason: str
    rms: float | None = None

    def to_dict(self) -> dict:
        return {"index": self.index, "name": self.name, "corners": self.corners, "status": self.status,
                "stage": self.stage, "reason": self.reason, "rms": self.rms}


@dataclass
class SelectionOptions:
    """Knobs of view selection and outlier rejection (see the module docstring)."""

    min_corners: int = 6
    min_views: int = 6
    max_views: int = 80  # the CLI's default too: the evaluation calibrates as a user does
    blur_ratio: float = 0.35
    duplicate_px: float | None = None  # default: 1 % of the image diagonal
    corner_outlier: float = 5.0
    view_outlier: float = 3.0
    border_px: float = 0.0  # corners nearer the image's border than this are not used (`border_margin`)
    select_terms: bool = True  # hold p1 p2 at 0 where held-out views are predicted as well without them (`select_terms`)
    weight_views: bool = True  # weigh each view by the spread of its own residuals (`weigh_views`)
    weight_corners: bool = True  # ... and each corner by its detector's covariance, where the detector gives them
    weight_spread: float = VIEW_WEIGHT_SPREAD  # views within this x the median view's spread keep their full weight


# RefineNet refines a corner from the 24 x 24 patch around its pixel (12 px each way): nearer the image's
# border, part of that patch is padding. On the rendered validation sequences (seed 0) the deep detector's
# corners within 8 px of the border were 3-4 x less accurate (0.32-0.51 px RMS against 0.12-0.15 px) and
# dropping those within the patch's reach brought the good-light calibrations within 0.3 % / 1 px on all
# three cameras (two of three with them); at 1 lux and under shake fx/fy stayed within 1 % (the principal
# point moved by up to 1.5 px either way: fewer corners where distortion is strongest).
REFINENET_BORDER_PX = 12.0


def border_margin(refine: str) -> float:
    """The default ``border_px`` for corners refined by ``refine`` ("refinenet" | "subpix" | "none"):
    OpenCV's detector finds no corner whose markers leave the image, so only RefineNet's need one."""
    return REFINENET_BORDER_PX if refine == "refinenet" else 0.0


def within_border(frame: FrameDetection, image_size: tuple[int, int], border_px: float) -> FrameDetection:
    """``frame`` without its corners nearer than ``border_px`` to the image's border (pixel centres at 0 .. W-1)."""
    if border_px <= 0 or len(frame.ids) == 0:
        return frame
    width, height = image_size
    x, y = frame.corners[:, 0], frame.corners[:, 1]
    inside = (x >= border_px - 0.5) & (y >= border_px - 0.5) & (x <= width - 0.5 - border_px) & (y <= height - 0.5 - border_px)
    return frame.subset(inside)


# ----------------------------------------------------------------------------------------- per frame
def sharpness(gray: np.ndarray, corners: np.ndarray) -> float:
    """Contrast-independent sharpness of the board's region of a uint8 (H, W) frame: the variance of the
    Laplacian over the variance of the pixels, in the corners' bounding box (grown by 10 %), after a
    Gaussian of sigma 1 px that takes out pixel noise (a dark, noisy frame must not look sharp).
    Motion and focus blur lower it; a uniform gain does not change it. 0 without corners."""
    corners = np.asarray(corners, np.float64).reshape(-1, 2)
    if len(corners) == 0:
        return 0.0
    low, high = corners.min(0), corners.max(0)
    grow = 0.1 * (high - low) + 4.0
    x0, y0 = np.maximum(np.floor(low - grow).astype(int), 0)
    x1, y1 = np.minimum(np.ceil(high + grow).astype(int) + 1, (gray.shape[1], gray.shape[0]))
    region = cv2.GaussianBlur(gray[y0:y1, x0:x1].astype(np.float32), (0, 0), 1.0)
    if region.size < 16:
        return 0.0
    return float(cv2.Laplacian(region, cv2.CV_32F).var() / (region.var() + 1.0))


def usable_reason(frame: FrameDetection, board: BoardSpec, min_corners: int) -> str | None:
    """None when the frame can be a calibration view, else why not (in words)."""
    if len(frame.ids) == 0:
        return "no board found"
    if len(frame.ids) < min_corners:
        return f"{len(frame.ids)} corners (fewer than {min_corners})"
    points = board.object_points()[frame.ids, :2]
    spread = np.linalg.svd(points - points.mean(0), compute_uv=False)
    if spread[1] < MIN_SPREAD_RATIO * spread[0]:
        return "corners along one line of the board"
    return None


# ----------------------------------------------------------------------------------------- selection
def initial_camera(frames: list[FrameDetection], board: BoardSpec, image_size: tuple[int, int]) -> np.ndarray:
    """(3, 3) rough K for view features: OpenCV's closed form from the views' homographies
    (``cv2.initCameraMatrix2D``) when it is plausible, else a 60-degree camera centred in the image."""
    width, height = image_size
    guess = np.array([[width / (2 * math.tan(math.radians(30))), 0, (width - 1) / 2],
                      [0, width / (2 * math.tan(math.radians(30))), (height - 1) / 2], [0, 0, 1.0]])
    if len(frames) < 2:
        return guess
    try:
        K = cv2.initCameraMatrix2D([board.object_points()[f.ids].astype(np.float32) for f in frames],
                                   [f.corners.astype(np.float32) for f in frames], (width, height))
    except cv2.error:
        return guess
    focal = K[0, 0]
    if not np.all(np.isfinite(K)) or not 0.2 * width < focal < 20 * width or not 0.5 < K[1, 1] / focal < 2:
        return guess
    return K


def view_features(frame: FrameDetection, board: BoardSpec, K: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """(6,) where and how the board is seen: centroid (x / W, y / H), log of its image size over the
    image's, and its normal's (x, y, z) in the camera frame (from a pinhole PnP with ``K``)."""
    width, height = image_size
    points = board.object_points()[frame.ids]
    ok, rvec, _ = cv2.solvePnP(points, frame.corners, K, None, flags=cv2.SOLVEPNP_IPPE)
    normal = cv2.Rodrigues(rvec)[0][:, 2] if ok else np.array([0.0, 0.0, 1.0])
    hull = cv2.convexHull(frame.corners.astype(np.float32))
    size = math.log(max(cv2.contourArea(hull), 1.0) / (width * height))
    centre = frame.corners.mean(0) / (width, height)
    return np.array([centre[0], centre[1], size, *normal])


def tilt_spread_deg(normals: np.ndarray) -> float:
    """Largest angle (degrees) between two of the (V, 3) unit board normals."""
    if len(normals) < 2:
        return 0.0
    cosines = np.clip(normals @ normals.T, -1.0, 1.0)
    return float(np.degrees(np.arccos(cosines.min())))


# Farthest-point metric: a move across the whole image counts like a 30-degree change of tilt
# (2 x the normal's sine) and a 2.7x change of the board's image area.
FEATURE_WEIGHTS = np.array([1.0, 1.0, 0.5, 2.0, 2.0, 2.0])


def select_views(frames: list[FrameDetection], board: BoardSpec, image_size: tuple[int, int],
                 options: SelectionOptions) -> tuple[list[FrameDetection], dict[int, tuple[str, str]]]:
    """The views to calibrate from, in frame order, and why each other frame was left out
    ({frame index: (stage, reason)}). Raises CalibrationError when too few are usable."""
    reasons: dict[int, tuple[str, str]] = {}
    candidates = []
    for frame in frames:
        reason = usable_reason(frame, board, options.min_corners)
        if reason:
            reasons[frame.index] = ("detection", reason)
        else:
            candidates.append(frame)
    _check_enough(frames, candidates, reasons, options)

    median_sharpness = float(np.median([f.sharpness for f in candidates]))
    sharp = []
    for frame in candidates:
        if frame.sharpness < options.blur_ratio * median_sharpness:
            reasons[frame.index] = ("selection", f"blurred (sharpness {frame.sharpness:.3g}, median {median_sharpness:.3g})")
        else:
            sharp.append(frame)

    width, height = image_size
    duplicate_px = options.duplicate_px if options.duplicate_px is not None else 0.01 * math.hypot(width, height)
    # Fullest and sharpest first: of near-duplicates, that one stays.
    ranked = sorted(sharp, key=lambda f: (-len(f.ids), -f.sharpness, f.index))
    distinct: list[FrameDetection] = []
    for frame in ranked:
        twin = next((kept for kept in distinct if _near_duplicate(frame, kept, duplicate_px)), None)
        if twin is None:
            distinct.append(frame)
        else:
            reasons[frame.index] = ("selection", f"near-duplicate of frame {twin.name}")
    _check_enough(frames, distinct, reasons, options)

    K0 = initial_camera(distinct, board, image_size)
    features = np.stack([view_features(f, board, K0, image_size) for f in distinct]) * FEATURE_WEIGHTS
    quality = np.sqrt(np.array([len(f.ids) for f in distinct]) / board.num_corners)
    chosen = [0]  # the fullest, sharpest view
    nearest = np.linalg.norm(features - features[0], axis=1)
    while len(chosen) < min(options.max_views, len(distinct)):
        score = nearest * quality
        score[chosen] = -1.0
        pick = int(np.argmax(score))
        chosen.append(pick)
        nearest = np.minimum(nearest, np.linalg.norm(features - features[pick], axis=1))
    for i, frame in enumerate(distinct):
        if i not in chosen:
            closest = min(chosen, key=lambda c: np.linalg.norm(features[c] - features[i]))
            reasons[frame.index] = ("selection", f"not needed (--max-views {options.max_views}): like frame "
                                                 f"{distinct[closest].name}")
    selected = sorted((distinct[i] for i in chosen), key=lambda f: f.index)
    normals = features[chosen, 3:] / FEATURE_WEIGHTS[3:]
    spread = tilt_spread_deg(normals)
    if spread < MIN_TILT_SPREAD_DEG:
        raise CalibrationError(
            f"all {len(selected)} usable views show the board at one tilt (within {spread:.0f} degrees), so the focal "
            f"length cannot be told from the distance: capture the board tilted 20-40 degrees towards each side and "
            f"in every part of the image")
    return selected, reasons


def _near_duplicate(a: FrameDetection, b: FrameDetection, tolerance_px: float) -> bool:
    common, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
    if len(common) < 0.8 * max(len(a.ids), len(b.ids)):
        return False
    return float(np.linalg.norm(a.corners[ia] - b.corners[ib], axis=1).mean()) < tolerance_px


def _check_enough(frames: list[FrameDetection], candidates: list[FrameDetection],
                  reasons: dict[int, tuple[str, str]], options: SelectionOptions) -> None:
    if len(candidates) >= options.min_views:
        return
    with_corners = [f for f in frames if len(f.ids)]
    if not frames:
        raise CalibrationError("no frames were read: give a video, a folder of images or a camera index that delivers frames")
    if not with_corners:
        raise CalibrationError(
            f"no board found in any of {len(frames)} frames: check --board (squares, dictionary, an inverted print) "
            f"and capture the board filling a quarter of the image or more, in focus and lit")
    collinear = sum(reasons.get(f.index, ("", ""))[1].startswith("corners along") for f in with_corners)
    duplicates = sum(reasons.get(f.index, ("", ""))[1].startswith("near-duplicate") for f in with_corners)
    hint = ""
    if collinear and collinear == len(with_corners) - len(candidates):
        hint = f"; {collinear} frame(s) show only one row or column of corners: show more of the board"
    elif duplicates and duplicates >= len(candidates):
        # A still board (or a still camera) gives one view however many frames are read.
        hint = (f"; {duplicates} frame(s) repeat a pose already kept: move and tilt the board between frames, "
                f"a calibration needs the board in several poses")
    raise CalibrationError(
        f"only {len(candidates)} usable view(s) (>= {options.min_corners} corners, not along one line, distinct, sharp) "
        f"in {len(frames)} frames where {options.min_views} are needed{hint}: capture the board at more places and "
        f"tilts, moving slowly, with most of it in view")


def coverage(views: list[FrameDetection], image_size: tuple[int, int], bins: tuple[int, int] = (8, 6)) -> float:
    """Fraction of the cells of a ``bins`` grid over the image that hold at least one of the views' corners."""
    width, height = image_size
    corners = np.concatenate([v.corners for v in views]) if views else np.zeros((0, 2))
    counts, _, _ = np.histogram2d(corners[:, 0], corners[:, 1], bins=bins, range=[[-0.5, width - 0.5], [-0.5, height - 0.5]])
    return float((counts > 0).mean())


def coverage_notes(views: list[FrameDetection], image_size: tuple[int, int]) -> list[str]:
    share = coverage(views, image_size)
    if share >= MIN_COVERAGE:
        return []
    return [f"the corners cover only {100 * share:.0f} % of the image (8 x 6 cells): the distortion beyond them is "
            f"extrapolated; capture the board near the image's edges and corners too"]
