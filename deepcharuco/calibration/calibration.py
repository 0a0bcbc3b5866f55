"""Camera calibration from ChArUco detections: view selection, OpenCV's solvers, outlier rejection.

The steps (each a function, `calibrate` runs them in order):

0. `within_border`: corners nearer the image's border than ``border_px`` are not used (RefineNet's,
   `border_margin`: its patch reaches past the border there);
1. `usable_reason`: a frame is a candidate view when it has at least ``min_corners`` corners
   that do not lie along one line of the board (one line leaves the tilt about it unobservable);
2. `select_views`: candidates blurred well below the others (`sharpness`, less than
   ``blur_ratio`` x the median) are dropped, then near-duplicates (most corners shared, the
   shared ones within ``duplicate_px``; the sharper, fuller view stays), then at most
   ``max_views`` views are picked by farthest-point sampling over where the board is in the
   image, how large, and how it is tilted (`view_features`), each view's distance weighted by
   its share of the board's corners: coverage of the image and of tilt, not 40 copies of one pose;
3. `solve`: ``cv2.calibrateCameraExtended`` on the corners (ID i at ``board.object_points()[i]``)
   for the ``pinhole`` (k1 k2 p1 p2 k3) and ``rational`` (+ k4 k5 k6) models, with the parameters'
   standard deviations; ``cv2.fisheye.calibrate`` for ``fisheye`` (k1..k4, no deviations);
4. outliers: the worst corner of each view, when its residual exceeds ``corner_outlier`` x the
   RMS (and 1 px), is dropped, then views whose RMS exceeds ``view_outlier`` x the median view RMS (and `MIN_OUTLIER_PX`), and
   it is solved again, until nothing changes (at most `MAX_ROUNDS`). The pinhole and rational
   models go through this twice: first with k3 (k4..k6) held at 0 (`STIFF`), then free, started
   from the first stage's solution;
5. `select_terms` (pinhole and rational, ``select_terms``, at least `MIN_SELECTION_VIEWS` views): the
   tangential terms p1 p2 are held at 0 when that predicts views left out of the fit (5-fold
   cross-validation over the kept views) at least as well as solving them; they trade against the
   principal point, so where the views cannot tell the two apart they only add noise to cx and cy;
6. `weigh_views` (pinhole and rational, ``weight_views``): the last solve weighs each view by the spread of its
   own residuals: a view whose residuals spread more than `VIEW_WEIGHT_SPREAD` x the median view's, in some
   direction, counts less in that direction (motion blur smears a view's corners along the blur, and the views
   of a shaken video differ by far more than their corner counts).

Bad input raises `CalibrationError` with one line saying what to capture instead: no board in any
frame, fewer usable views than ``min_views``, all views at one tilt (the focal length is then not
observable), or a solution whose focal length is uncertain by more than `MAX_RELATIVE_STD`.

Pixels: OpenCV's convention (centre of the top-left pixel at (0, 0)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.core.checks import check_choice
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.core.errors import OptionError
from deepcharuco.core.opencv_api import fisheye_calibration_flags
from deepcharuco.geometry.camera import Camera
from deepcharuco.geometry.pose import MIN_SPREAD_RATIO

MODELS = ("pinhole", "rational", "fisheye")
MAX_ROUNDS = 6  # solves per stage; outliers are rejected between them
# The first stage of every pinhole and rational calibration: k3 (and k4..k6) at 0. Outliers are judged
# under this model first: one that can bend its edges with k3 bends them to meet a wrong corner there
# (a corner the deep detector put 17 px off, at the image's edge, took a free-k3 solve to fx 0.7 % and
# cy 4 px off the rendered truth; judged under the stiff model it was dropped and the lens recovered).
STIFF = ("pinhole", True)
MIN_COVERAGE = 0.5  # below this share of the image holding corners, the result says the distortion is extrapolated
MIN_OUTLIER_PX = 0.5  # a view within this RMS is never an outlier: cornerSubPix noise alone reaches it
MIN_TILT_SPREAD_DEG = 10.0  # Zhang's method needs at least two board orientations this far apart
MAX_RELATIVE_STD = 0.05  # a focal length less certain than 5 % is not a calibration
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
# Names of calibrateCameraExtended's 18 intrinsic standard deviations, in its order.
STD_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4", "tau_x", "tau_y")


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


@dataclass
class CalibrationResult:
    """A solved calibration.

    Attributes:
        model: "pinhole" | "rational" | "fisheye".
        camera: the intrinsics (K, dist (5, 8 or 4 fisheye coefficients), image size).
        rms: RMS reprojection error (px) over every corner used.
        std: standard deviation of each intrinsic parameter by name (`STD_NAMES`), empty for fisheye.
        views: the kept views, in frame order, with per_view_rms (V,), rvecs/tvecs (V, 3), and
            residuals: per view (N_v, 2) float64 detected minus reprojected pixels of its used corners.
        decisions: one `ViewDecision` per frame of the source.
        frames: frames read; image_size: (width, height).
    """

    model: str
    camera: Camera
    rms: float
    std: dict[str, float]
    views: list[FrameDetection]
    per_view_rms: np.ndarray
    rvecs: np.ndarray
    tvecs: np.ndarray
    residuals: list[np.ndarray]
    decisions: list[ViewDecision]
    frames: int
    rounds: int = 1
    notes: list[str] = field(default_factory=list)
    terms: str = ""  # the distortion terms solved, e.g. "k1 k2 p1 p2 k3" (the others held at 0)
    held_out: dict[str, float] = field(default_factory=dict)  # `select_terms`' score of each candidate (terms -> px)
    # `weigh_views`: per kept view, its weight along its noisiest direction (1: a full view; empty: equal weights)
    view_weights: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def image_size(self) -> tuple[int, int]:
        return self.camera.image_size

    @property
    def corner_sigma(self) -> float:
        """Per-corner uncertainty: the standard deviation (px, per axis) of one detected corner about where the
        solved camera puts it, from the residuals with the solved parameters' degrees of freedom taken out
        (2N measurements, 6 per view and the intrinsics solved). The residual RMS alone understates it: the
        fit absorbs part of the noise, most where a view has few corners. Assumes every corner of a detector
        is alike; a detector's bad corners show in `residuals`."""
        count = sum(len(r) for r in self.residuals)
        # `std` names exactly the intrinsics that were solved (not a fixed k3); the fisheye solver gives none.
        solved = 6 * len(self.residuals) + (len(self.std) if self.std else 4 + len(self.camera.dist))
        freedom = 2 * count - solved
        if freedom <= 0:
            return math.nan
        return math.sqrt(float(sum(np.sum(r ** 2) for r in self.residuals)) / freedom)

    def summary(self) -> dict:
        """JSON-ready numbers: intrinsics, deviations, RMS, view counts."""
        K = self.camera.K
        return {"model": self.model, "image_size": list(self.image_size), "rms_px": self.rms,
                "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "dist": self.camera.dist.tolist(),
                "std": self.std, "corner_sigma_px": self.corner_sigma, "frames": self.frames, "views_kept": len(self.views),
                "frames_with_corners": sum(d.corners > 0 for d in self.decisions), "rounds": self.rounds,
                "terms": self.terms, "held_out_px": self.held_out,
                "views_weighed_down": int(np.sum(self.view_weights < 0.5))}  # less than half


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


# ----------------------------------------------------------------------------------------- solving
@dataclass
class _Solution:
    K: np.ndarray
    dist: np.ndarray
    rvecs: np.ndarray
    tvecs: np.ndarray
    std: dict[str, float]


def _flags(model: str, fix_k3: bool, zero_tangent: bool = False) -> int:
    if model not in ("pinhole", "rational"):
        raise OptionError(f"model must be one of {MODELS}, got {model!r}")
    # k3 fixed at 0: the usual choice for webcam lenses and few views, where a free k3 fits the noise
    # and bends the model where no corner was seen. Tangential terms at 0: see `select_terms`.
    return ((cv2.CALIB_RATIONAL_MODEL if model == "rational" else 0) | (cv2.CALIB_FIX_K3 if fix_k3 else 0)
            | (cv2.CALIB_ZERO_TANGENT_DIST if zero_tangent else 0))


def solve(object_points: list[np.ndarray], image_points: list[np.ndarray], image_size: tuple[int, int],
          model: str, fix_k3: bool = False, guess: _Solution | None = None, zero_tangent: bool = False) -> _Solution:
    """One solve of OpenCV's calibration. object_points[v]: (N_v, 3), image_points[v]: (N_v, 2).
    ``fix_k3``: keep k3 at 0 (pinhole and rational models). ``guess``: a solution to start from
    (pinhole and rational models). ``zero_tangent``: keep p1 and p2 at 0 (pinhole and rational).

    Without a guess, a model with k3 (or k4..k6) free is solved in two stages: first with them held
    at 0 (`STIFF`), then free from there. Started from no distortion at all, OpenCV's
    Levenberg-Marquardt can settle where k2 and k3 cancel each other."""
    try:
        if model == "fisheye":
            return _solve_fisheye(object_points, image_points, image_size)
        objects = [p.astype(np.float32) for p in object_points]
        images = [p.astype(np.float32) for p in image_points]
        if guess is None:
            first = _solve_opencv(objects, images, image_size, _flags(*STIFF, zero_tangent), None, None)
            if (model, fix_k3) == STIFF:
                return _named(first, model, fix_k3, zero_tangent)
            guess = _named(first, *STIFF, zero_tangent)
        else:
            first = None
        second = _solve_opencv(objects, images, image_size,
                               _flags(model, fix_k3, zero_tangent) | cv2.CALIB_USE_INTRINSIC_GUESS,
                               guess.K, _held(guess.dist, model, fix_k3, zero_tangent))
    except cv2.error as exc:
        raise CalibrationError(f"OpenCV's {model} calibration failed ({str(exc).strip().splitlines()[-1]}): capture "
                               f"more views covering the whole image at varied tilts") from None
    # Levenberg-Marquardt only ever lowers the error from its start, but the extrinsics are started afresh:
    # should the freer model end worse, the first stage's solution is the better one of this model too.
    if first is not None and second[5] > first[5] + 1e-9:
        return _named(first, model, fix_k3, zero_tangent)
    return _named(second, model, fix_k3, zero_tangent)


def _held(dist: np.ndarray, model: str, fix_k3: bool, zero_tangent: bool) -> np.ndarray:
    """``dist`` as a start for a solve of (model, fix_k3, zero_tangent): OpenCV keeps a fixed term at its
    starting value, so the terms that model holds are set to 0 (and a pinhole's k4..k6 stay 0)."""
    dist = np.pad(np.asarray(dist, np.float64).ravel(), (0, 14)).copy()[:14]
    if zero_tangent:
        dist[2:4] = 0.0
    if fix_k3:
        dist[4] = 0.0
    if fix_k3 or model == "pinhole":
        dist[5:8] = 0.0
    return dist


def _solve_opencv(objects: list[np.ndarray], images: list[np.ndarray], image_size: tuple[int, int], flags: int,
                  K: np.ndarray | None, dist: np.ndarray | None) -> tuple:
    """(K, dist (14,), rvecs, tvecs, std (18,), rms) of ``cv2.calibrateCameraExtended``."""
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    if K is not None:
        K = K.copy()
        dist = np.pad(np.asarray(dist, np.float64).ravel(), (0, max(0, 14 - np.asarray(dist).size)))
    rms, K, dist, rvecs, tvecs, std, _, _ = cv2.calibrateCameraExtended(objects, images, image_size, K, dist,
                                                                       flags=flags, criteria=criteria)
    dist = np.pad(np.asarray(dist, np.float64).ravel(), (0, max(0, 14 - np.asarray(dist).size)))
    return K, dist, rvecs, tvecs, np.asarray(std, np.float64).ravel(), float(rms)


def _intrinsic_names(model: str) -> tuple[str, ...]:
    """The pinhole or rational model's intrinsics in `STD_NAMES` order: fx fy cx cy and its distortion terms."""
    return STD_NAMES[:4 + (5 if model == "pinhole" else 8)]


def _named(raw: tuple, model: str, fix_k3: bool, zero_tangent: bool = False) -> _Solution:
    K, dist, rvecs, tvecs, std_intrinsics, _ = raw
    names = _intrinsic_names(model)
    count = len(names) - 4
    std = {name: float(v) for name, v in zip(names, std_intrinsics[:len(names)])
           if not (fix_k3 and name == "k3") and not (zero_tangent and name in ("p1", "p2"))
           and not (v == 0.0 and name in ("k3", "k4", "k5", "k6"))}
    return _Solution(K=np.asarray(K, np.float64), dist=dist[:count].copy(),
                     rvecs=np.asarray(rvecs, np.float64).reshape(-1, 3), tvecs=np.asarray(tvecs, np.float64).reshape(-1, 3),
                     std=std)


def _solve_fisheye(object_points: list[np.ndarray], image_points: list[np.ndarray],
                   image_size: tuple[int, int]) -> _Solution:
    flags = fisheye_calibration_flags()
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-10)
    # (1, N, 3) and (1, N, 2): OpenCV 5's fisheye calibration fails on OpenCV 4's (N, 1, 3) with "Sizes of input
    # arguments do not match"; both take these
    _, K, dist, rvecs, tvecs = cv2.fisheye.calibrate(
        [p.reshape(1, -1, 3).astype(np.float64) for p in object_points],
        [p.reshape(1, -1, 2).astype(np.float64) for p in image_points], image_size, None, None,
        flags=flags, criteria=criteria)
    return _Solution(K=np.asarray(K, np.float64), dist=np.asarray(dist, np.float64).ravel(),
                     rvecs=np.asarray(rvecs, np.float64).reshape(-1, 3), tvecs=np.asarray(tvecs, np.float64).reshape(-1, 3),
                     std={})


def reproject(object_points: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, K: np.ndarray, dist: np.ndarray,
              model: str) -> np.ndarray:
    """(N, 2) pixels of the (N, 3) board points under a pose and intrinsics of ``model``."""
    if model == "fisheye":
        points, _ = cv2.fisheye.projectPoints(object_points.reshape(-1, 1, 3), rvec.reshape(3, 1),
                                              tvec.reshape(3, 1), K, dist)
    else:
        points, _ = cv2.projectPoints(object_points, rvec, tvec, K, dist)
    return points.reshape(-1, 2)


def _residuals(object_points: list[np.ndarray], image_points: list[np.ndarray], solution: _Solution, model: str
               ) -> tuple[list[np.ndarray], list[np.ndarray], float, np.ndarray]:
    """Each view's residuals (N_v, 2) (detected minus reprojected, px), their norms (N_v,), the RMS over all
    corners and each view's RMS (V,)."""
    residuals = [image - reproject(points, r, t, solution.K, solution.dist, model)
                 for points, image, r, t in zip(object_points, image_points, solution.rvecs, solution.tvecs)]
    norms = [np.linalg.norm(r, axis=1) for r in residuals]
    rms = float(np.sqrt(np.mean(np.concatenate(norms) ** 2)))
    return residuals, norms, rms, np.array([math.sqrt(float(np.mean(n ** 2))) for n in norms])


def calibrate(frames: list[FrameDetection], board: BoardSpec, image_size: tuple[int, int], model: str = "pinhole",
              options: SelectionOptions | None = None, *, fix_k3: bool = False) -> CalibrationResult:
    """Select views from ``frames``, solve, reject outliers and re-solve (module docstring). ``fix_k3``:
    keep k3 at 0 (not for fisheye)."""
    if fix_k3 and model == "fisheye":
        raise OptionError("fix_k3 applies to the pinhole and rational models, not fisheye")
    check_choice("model", model, MODELS)
    options = options or SelectionOptions()
    trimmed = [within_border(f, image_size, options.border_px) for f in frames]
    at_border = {f.index: len(f.ids) - len(t.ids) for f, t in zip(frames, trimmed) if len(f.ids) > len(t.ids)}
    views, reasons = select_views(trimmed, board, image_size, options)
    for index, count in at_border.items():
        if index in reasons and reasons[index][0] == "detection":
            reasons[index] = ("detection", f"{reasons[index][1]} after {count} within {options.border_px:g} px of the "
                                           f"border")
    # Per view: the mask of its corners still in use.
    masks = {v.index: np.ones(len(v.ids), bool) for v in views}
    outliers: dict[int, str] = {}
    dropped_corners: dict[int, int] = {}
    stages = [(model, fix_k3)] if model == "fisheye" or (model, fix_k3) == STIFF else [STIFF, (model, fix_k3)]
    solution, rounds = None, 0
    for stage_model, stage_fix_k3 in stages:
        for stage_round in range(1, MAX_ROUNDS + 1):
            rounds += 1
            active = [v for v in views if v.index not in outliers]
            objects = [board.object_points()[v.ids[masks[v.index]]] for v in active]
            images = [v.corners[masks[v.index]] for v in active]
            solution = solve(objects, images, image_size, stage_model, stage_fix_k3, guess=solution)
            residuals, norms, rms, view_rms = _residuals(objects, images, solution, stage_model)
            if stage_round == MAX_ROUNDS or not _reject_outliers(active, norms, view_rms, rms, masks, outliers,
                                                                 dropped_corners, options):
                break
    terms, held_out = terms_name(model, fix_k3, False), {}
    if model != "fisheye" and options.select_terms and len(active) >= MIN_SELECTION_VIEWS:
        zero_tangent, scores = select_terms(objects, images, image_size, model, fix_k3, solution)
        held_out = {terms_name(model, fix_k3, zt): score for zt, score in scores.items()}
        if zero_tangent:
            terms = terms_name(model, fix_k3, True)
            solution = solve(objects, images, image_size, model, fix_k3, guess=solution, zero_tangent=True)
            residuals, norms, rms, view_rms = _residuals(objects, images, solution, model)
    view_weights = np.zeros(0)
    if model != "fisheye" and options.weight_views and len(active) >= MIN_WEIGHTED_VIEWS:
        covariances = [v.covariances[masks[v.index]] for v in active] \
            if options.weight_corners and all(v.covariances is not None for v in active) else None
        solution, view_weights = weigh_views(objects, images, solution, model, terms, options.weight_spread,
                                             corner_covariances=covariances)
        residuals, norms, rms, view_rms = _residuals(objects, images, solution, model)
    if model != "fisheye" and len(active) >= MIN_BOOTSTRAP_VIEWS:
        solution.std.update({name: value for name, value in
                             bootstrap_std(objects, images, image_size, model, terms, solution).items()
                             if value > solution.std.get(name, 0.0)})
    _check_solution(solution, model, image_size)
    decisions = []
    kept_rms = dict(zip((v.index for v in active), view_rms))
    for frame in frames:
        if frame.index in kept_rms:
            extra = f"; {dropped_corners[frame.index]} outlier corner(s) dropped" if frame.index in dropped_corners else ""
            if frame.index in at_border:
                extra += f"; {at_border[frame.index]} corner(s) within {options.border_px:g} px of the border unused"
            decisions.append(ViewDecision(frame.index, frame.name, len(frame.ids), "kept", "solution",
                                          "calibration view" + extra, float(kept_rms[frame.index])))
        elif frame.index in outliers:
            decisions.append(ViewDecision(frame.index, frame.name, len(frame.ids), "dropped", "outlier", outliers[frame.index]))
        else:
            stage, reason = reasons[frame.index]
            decisions.append(ViewDecision(frame.index, frame.name, len(frame.ids), "dropped", stage, reason))
    used_views = [v.subset(masks[v.index]) for v in active]
    camera = Camera(K=solution.K, dist=solution.dist, image_size=image_size,
                    model="fisheye" if model == "fisheye" else "pinhole")
    fold = fold_share(camera)
    fold_notes = []
    if fold is not None:
        where = (f"the solved distortion folds back {100 * fold:.0f} % of the way out to the image's farthest corner, "
                 f"so the image beyond cannot be undistorted")
        if fold >= MIN_FOLD_SHARE or model == "rational":  # rational: k3 alone is not what folds it, a note only
            fold_notes.append(f"{where}" + (" (the corners' tips only)" if fold >= MIN_FOLD_SHARE else
                                            ": do not undistort beyond it; capture the board near the image's edges "
                                            "and corners too"))
        elif not fix_k3:  # a free k3 is what bends the model where the views have no corners: solve without it
            result = calibrate(frames, board, image_size, model, options, fix_k3=True)
            result.notes.insert(0, f"with k3 free {where}: solved again with k3 fixed at 0")
            return result
        else:
            raise CalibrationError(f"{where}: capture the board near the image's edges and corners too "
                                   f"({100 * coverage(used_views, image_size):.0f} % of the image is covered)")
    return CalibrationResult(model=model, camera=camera, rms=rms, std=solution.std, views=used_views,
                             per_view_rms=view_rms, rvecs=solution.rvecs, tvecs=solution.tvecs, residuals=residuals,
                             decisions=decisions, frames=len(frames), rounds=rounds,
                             notes=(["k3 fixed at 0"] if fix_k3 else []) + _coverage_notes(used_views, image_size)
                             + fold_notes,
                             terms=terms, held_out=held_out, view_weights=view_weights)


# ----------------------------------------------------------------------------------------- distortion terms
# Whether the views support the tangential terms p1 p2, chosen by cross-validation over views. p1 p2 move the
# image much as a shift of the principal point does, so where the views cannot tell the two apart, free p1 p2
# only add noise to cx and cy: on the rendered test camera that missed (seed 1, k1 +0.1, 55 degrees of field,
# 75 views) exact corners + 0.1 px noise put cx within +-0.7 px (one standard deviation) with p1 p2 free and
# +-0.2 px with them at 0. Where the lens has them (p ~ 1e-3: the validation k1 -0.15 camera) holding them at 0
# costs ~1 px of cx, and the held-out views say so (their error rises 1.4 %). Chosen on the validation renders
# (seed 0): deciding k3 (k4..k6) the same way was tried too and left out: it changed nothing on average (noise
# simulations) and moved the blurred k1 -0.15 shake sequence's fx from -0.90 % to -1.10 % of the truth.
SELECTION_FOLDS = 5  # views are dealt round-robin (in frame order) into this many folds
MIN_SELECTION_VIEWS = 10  # fewer views: every term of the model is solved, nothing is held out


def terms_name(model: str, fix_k3: bool, zero_tangent: bool) -> str:
    """The distortion terms a solve of (model, fix_k3, zero_tangent) frees, e.g. "k1 k2 p1 p2 k3"."""
    if model == "fisheye":
        return "k1 k2 k3 k4"
    names = ["k1", "k2"] + ([] if zero_tangent else ["p1", "p2"]) + ([] if fix_k3 else ["k3"])
    return " ".join(names + (["k4", "k5", "k6"] if model == "rational" else []))


def select_terms(object_points: list[np.ndarray], image_points: list[np.ndarray], image_size: tuple[int, int],
                 model: str, fix_k3: bool, solution: _Solution, folds: int = SELECTION_FOLDS
                 ) -> tuple[bool, dict[bool, float]]:
    """Whether to hold p1 p2 at 0 (pinhole and rational models), by how well each choice predicts views it was
    not fitted to.

    The views are dealt round-robin into ``folds`` folds; each choice is solved (from ``solution``) on all folds
    but one, and each view of the held-out fold gets its own pose (``cv2.solvePnP``) under those intrinsics: its
    score is the held-out residuals' RMS per axis (px), the poses' 6 degrees of freedom taken out. Whole views are
    held out, so errors shared by a view's corners (blur) count as they do in use. No truth is involved.

    Returns (zero_tangent: True when p1 p2 at 0 predict the held-out views at least as well, {zero_tangent: score})."""
    objects = [p.astype(np.float32) for p in object_points]
    images = [p.astype(np.float32) for p in image_points]
    # Started from the whole set's solution, 20 steps settle the scores to 1e-5 relative (on the validation renders)
    # at a fifth of the cost of the final solve's 100.
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 20, 1e-8)
    scores = {}
    for zero_tangent in (True, False):
        flags = _flags(model, fix_k3, zero_tangent) | cv2.CALIB_USE_INTRINSIC_GUESS
        start = _held(solution.dist, model, fix_k3, zero_tangent)
        squares, freedom = 0.0, 0
        for fold in range(folds):
            train = [i for i in range(len(objects)) if i % folds != fold]
            try:
                _, K, dist, _, _ = cv2.calibrateCamera([objects[i] for i in train], [images[i] for i in train],
                                                       image_size, solution.K.copy(), start.copy(), flags=flags,
                                                       criteria=criteria)
            except cv2.error:
                squares = math.inf
                break
            for i in range(fold, len(objects), folds):
                ok, rvec, tvec = cv2.solvePnP(objects[i], images[i], K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
                projected = cv2.projectPoints(objects[i], rvec, tvec, K, dist)[0].reshape(-1, 2)
                squares += float(np.sum((projected - images[i]) ** 2)) if ok else math.inf
                freedom += 2 * len(objects[i]) - 6
        scores[zero_tangent] = math.sqrt(squares / freedom) if freedom > 0 else math.inf
    # A tie goes to the simpler model.
    return scores[True] <= scores[False], scores


# ----------------------------------------------------------------------------------------- deviations
# The solver's deviations assume every corner errs independently; a view's corners err together (blur along one
# direction, a detector's bias at one tilt), and the views chosen decide more than their count says where they
# cover little of the image. Each parameter's reported deviation is the larger of the solver's and the spread of
# BOOTSTRAP_ROUNDS solves over views drawn with replacement (from the final solution, BOOTSTRAP_STEPS steps each).
# On caliscope's four webcams the bootstrap read 0.7-1.9 x the solver's deviations (cam_0's cx 5.9 -> 13.7 px).
BOOTSTRAP_ROUNDS = 20
BOOTSTRAP_STEPS = 30
MIN_BOOTSTRAP_VIEWS = 6


def bootstrap_std(object_points: list[np.ndarray], image_points: list[np.ndarray], image_size: tuple[int, int],
                  model: str, terms: str, solution: "_Solution", rounds: int = BOOTSTRAP_ROUNDS, seed: int = 0
                  ) -> dict[str, float]:
    """{name: standard deviation} of the pinhole or rational intrinsics ``terms`` solves (`terms_name`), over
    ``rounds`` OpenCV solves of views drawn with replacement, each started from ``solution`` (seeded: the same
    views give the same deviations)."""
    names = [n for n in _intrinsic_names(model) if n in ("fx", "fy", "cx", "cy") or n in terms.split()]
    flags = _flags(model, "k3" not in terms.split(), "p1" not in terms.split()) | cv2.CALIB_USE_INTRINSIC_GUESS
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, BOOTSTRAP_STEPS, 1e-10)
    objects = [p.astype(np.float32) for p in object_points]
    images = [p.astype(np.float32) for p in image_points]
    rng = np.random.default_rng(seed)
    values = []
    for _ in range(rounds):
        pick = rng.integers(0, len(objects), len(objects))
        try:
            _, K, dist, _, _ = cv2.calibrateCamera([objects[i] for i in pick], [images[i] for i in pick], image_size,
                                                   solution.K.copy(), np.pad(solution.dist, (0, 14 - solution.dist.size)),
                                                   flags=flags, criteria=criteria)
        except cv2.error:
            continue
        dist = np.asarray(dist, np.float64).ravel()
        everything = dict(zip(_intrinsic_names(model), [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist]))
        values.append([everything[name] for name in names])
    if len(values) < rounds // 2:
        return {}
    return dict(zip(names, (float(v) for v in np.std(np.array(values), axis=0, ddof=1))))


# ----------------------------------------------------------------------------------------- view weights
# Each view's corners are weighed by the spread of its own residuals (`weigh_views`; VIEW_WEIGHT_SPREAD above).
# Re-weigh from each weighted solution's residuals this many times (IRLS): on the 6 validation shake videos of seeds
# 0 and 3, 4 rounds give what 8 do to 0.001 % of fx (1 round: within 0.01 % and 0.12 px of it).
WEIGHT_ROUNDS = 4
# Fewer views: all weigh alike (the median view says too little of what a normal view is); the same floor as
# `select_terms`' (not tuned: every validation sequence has 21 views or more).
MIN_WEIGHTED_VIEWS = 10
LM_STEPS = 50  # Levenberg-Marquardt steps of one weighted solve (from OpenCV's solution; it stops when the cost settles)


def weigh_views(object_points: list[np.ndarray], image_points: list[np.ndarray], solution: _Solution, model: str,
                terms: str, spread: float = VIEW_WEIGHT_SPREAD, rounds: int = WEIGHT_ROUNDS,
                corner_covariances: list[np.ndarray] | None = None) -> tuple[_Solution, np.ndarray]:
    """The pinhole or rational solution refitted with each view weighed by its residuals' spread (iteratively
    reweighted least squares from ``solution``; `weighted_solve`), and each view's weight along its noisiest
    direction (V,) (1: full weight).

    A view's information matrix is the inverse of its residuals' 2 x 2 covariance (pose's degrees of freedom taken
    out), scaled so that a view within ``spread`` x the median view's standard deviation in every direction weighs
    as OpenCV weighs it (1) and a worse one less, only in its worse direction. ``terms`` names the distortion terms
    solved (`terms_name`); the others stay where ``solution`` has them (0).

    With ``corner_covariances`` (per view, (N, 2, 2) px^2: the detector's), each corner's information is instead the
    inverse of its own covariance plus its view's excess: the part of the view's residual covariance that its
    corners' covariances do not explain (a board's flex, a rolling shutter, a motion the detector did not see), so a
    sharp corner counts more than a blurred one of the same view and a view worse than its corners say counts
    less. A view's weight is then its information's smallest eigenvalue (mean over its corners) over the median
    view's."""
    names = _intrinsic_names(model)
    free = np.array([n in ("fx", "fy", "cx", "cy") or n in terms.split() for n in names])
    current = solution
    if corner_covariances is not None:
        return _weigh_corners(object_points, image_points, current, model, free, corner_covariances, rounds)
    information = [np.eye(2)] * len(object_points)
    for _ in range(rounds):
        residuals = _residuals(object_points, image_points, current, model)[0]
        sigma = np.array([math.sqrt(float(np.sum(r ** 2)) / max(2 * len(r) - 6, 1)) for r in residuals])
        floor = (spread * float(np.median(sigma))) ** 2
        if floor <= 0:
            break
        information = []
        for r in residuals:
            covariance = r.T @ r / max(len(r) - 3, 1)
            variance, axes = np.linalg.eigh(covariance)
            information.append((axes * (floor / np.maximum(variance, floor))) @ axes.T)
        current = weighted_solve(object_points, image_points, current, free, information)
    weights = np.minimum([float(np.linalg.eigvalsh(w)[0]) for w in information], 1.0)
    return current, weights


def _weigh_corners(object_points: list[np.ndarray], image_points: list[np.ndarray], solution: _Solution, model: str,
                   free: np.ndarray, corner_covariances: list[np.ndarray], rounds: int) -> tuple[_Solution, np.ndarray]:
    """`weigh_views` with each corner's covariance (its docstring)."""
    current = solution
    information = [np.linalg.inv(c) for c in corner_covariances]
    for _ in range(rounds):
        residuals = _residuals(object_points, image_points, current, model)[0]
        information = []
        for r, covariances in zip(residuals, corner_covariances):
            information.append(np.linalg.inv(covariances + view_excess(r, covariances)))
        current = weighted_solve(object_points, image_points, current, free, information)
    strength = np.array([float(np.linalg.eigvalsh(w.mean(axis=0))[0]) for w in information])
    return current, np.minimum(strength / max(float(np.median(strength)), 1e-300), 1.0)


def view_excess(residuals: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """(2, 2) px^2: the part of a view's residual covariance (``residuals`` (N, 2) px) that its corners' own
    ``covariances`` (N, 2, 2) do not explain (a motion the detector did not see, a board that flexes), positive
    semi-definite."""
    observed = residuals.T @ residuals / max(len(residuals) - 3, 1)  # the pose's 6 degrees of freedom over 2N residuals
    variance, axes = np.linalg.eigh(observed - covariances.mean(axis=0))
    return (axes * np.maximum(variance, 0.0)) @ axes.T


def weighted_solve(object_points: list[np.ndarray], image_points: list[np.ndarray], start: _Solution, free: np.ndarray,
                   information: list[np.ndarray]) -> _Solution:
    """Levenberg-Marquardt over the intrinsics marked ``free`` (in `STD_NAMES` order: fx fy cx cy k1 k2 p1 p2 k3
    [k4 k5 k6]) and every view's pose, minimising sum over views v and corners i of r_vi^T W_v r_vi (r: detected
    minus projected, W_v: the view's 2 x 2 ``information``, or (N, 2, 2): one per corner), from ``start``. OpenCV's
    calibration has no weights;
    this uses cv2.projectPoints' derivatives and eliminates the poses per view (Schur complement). ``std``: the
    free intrinsics' standard deviations from the weighted normal equations, scaled by the weighted residuals."""
    K, dist = start.K.copy(), start.dist.copy()
    rvecs, tvecs = start.rvecs.copy(), start.tvecs.copy()
    roots = [np.swapaxes(np.linalg.cholesky(w + 1e-12 * np.eye(2)), -1, -2) for w in information]  # W = L^T L
    objects = [p.astype(np.float64).reshape(-1, 3) for p in object_points]
    images = [p.astype(np.float64).reshape(-1, 2) for p in image_points]
    count = int(free.sum())

    def whitened(K, dist, rvecs, tvecs, derivatives: bool):
        out = []
        for points, image, r, t, root in zip(objects, images, rvecs, tvecs, roots):
            projected, jacobian = cv2.projectPoints(points, r, t, K, dist)
            difference = projected.reshape(-1, 2) - image
            residual = difference @ root.T if root.ndim == 2 else np.einsum("nij,nj->ni", root, difference)
            if derivatives:
                jacobian = np.einsum("ij,njk->nik" if root.ndim == 2 else "nij,njk->nik", root,
                                     jacobian.reshape(-1, 2, jacobian.shape[1]))
                jacobian = jacobian.reshape(-1, jacobian.shape[2])
                out.append((residual.reshape(-1), jacobian[:, :6], jacobian[:, 6:6 + len(free)][:, free]))
            else:
                out.append(residual)
        return out

    def cost(parts) -> float:
        return float(sum(np.sum(p ** 2) for p in parts))

    def normal_equations(parts):
        U, g = np.zeros((count, count)), np.zeros(count)
        blocks = []
        for residual, pose_jacobian, intrinsic_jacobian in parts:
            U += intrinsic_jacobian.T @ intrinsic_jacobian
            g += intrinsic_jacobian.T @ residual
            blocks.append((pose_jacobian.T @ pose_jacobian, intrinsic_jacobian.T @ pose_jacobian, pose_jacobian.T @ residual))
        return U, g, blocks

    current = cost(whitened(K, dist, rvecs, tvecs, False))
    damping = 1e-3
    for _ in range(LM_STEPS):
        U, g, blocks = normal_equations(whitened(K, dist, rvecs, tvecs, True))
        improved = False
        while damping < 1e8:
            reduced, rhs, inverses = U + damping * np.diag(np.diag(U)), -g.copy(), []
            for V, W, gv in blocks:
                inverse = np.linalg.inv(V + damping * np.diag(np.diag(V)))
                inverses.append(inverse)
                reduced -= W @ inverse @ W.T
                rhs += W @ inverse @ gv
            step = np.linalg.solve(reduced, rhs)
            full = np.zeros(len(free))
            full[free] = step
            K2 = K.copy()
            K2[0, 0] += full[0]
            K2[1, 1] += full[1]
            K2[0, 2] += full[2]
            K2[1, 2] += full[3]
            dist2 = dist + full[4:]
            poses = np.stack([inverse @ (-gv - W.T @ step) for (V, W, gv), inverse in zip(blocks, inverses)])
            rvecs2, tvecs2 = rvecs + poses[:, :3], tvecs + poses[:, 3:]
            trial = cost(whitened(K2, dist2, rvecs2, tvecs2, False))
            if trial < current:
                converged = current - trial < 1e-12 * max(current, 1e-300)
                K, dist, rvecs, tvecs, current = K2, dist2, rvecs2, tvecs2, trial
                damping = max(damping / 10, 1e-9)
                improved = True
                break
            damping *= 10
        if not improved or converged:
            break
    # Standard deviations: the weighted normal equations' inverse (poses eliminated), scaled by the residual variance.
    U, g, blocks = normal_equations(whitened(K, dist, rvecs, tvecs, True))
    for V, W, _ in blocks:
        U = U - W @ np.linalg.inv(V) @ W.T
    measurements = 2 * sum(len(p) for p in objects)
    freedom = measurements - count - 6 * len(objects)
    scale = current / freedom if freedom > 0 else math.nan
    try:
        deviations = np.sqrt(np.maximum(np.diag(np.linalg.inv(U)), 0.0) * scale)
    except np.linalg.LinAlgError:
        deviations = np.full(count, math.nan)
    names = [n for n, f in zip(STD_NAMES, free) if f]
    return _Solution(K=K, dist=dist, rvecs=rvecs, tvecs=tvecs, std=dict(zip(names, map(float, deviations))))


def _reject_outliers(active: list[FrameDetection], norms: list[np.ndarray], view_rms: np.ndarray, rms: float,
                     masks: dict[int, np.ndarray], outliers: dict[int, str], dropped_corners: dict[int, int],
                     options: SelectionOptions) -> bool:
    """Mark outlier corners (in ``masks``) and outlier views (in ``outliers``) of one solution; True when
    anything changed. Corners first: one wrong corner should cost itself, not its whole view."""
    changed = False
    corner_limit = max(options.corner_outlier * rms, 1.0)
    # A view that just lost corners is judged again after the re-solve: its pose was pulled by them.
    remaining_rms = view_rms.copy()
    for i, (view, norm) in enumerate(zip(active, norms)):
        bad = norm > corner_limit
        # The worst corner only, one a round: a wrong corner pulls its view's pose, and with it its neighbours'
        # residuals past the limit too. A view with many bad corners is judged whole, as a view, below.
        if bad.any() and bad.sum() <= max(1, len(norm) // 3) and masks[view.index].sum() > options.min_corners:
            used = np.flatnonzero(masks[view.index])
            masks[view.index][used[int(np.argmax(norm))]] = False
            dropped_corners[view.index] = dropped_corners.get(view.index, 0) + 1
            remaining_rms[i] = 0.0
            changed = True
    view_limit = max(options.view_outlier * float(np.median(view_rms)), MIN_OUTLIER_PX)
    remaining = len(active)
    for i in np.argsort(-remaining_rms):
        if remaining_rms[i] <= view_limit or remaining <= options.min_views:
            break
        outliers[active[i].index] = (f"outlier: RMS {remaining_rms[i]:.2f} px > {view_limit:.2f} px "
                                     f"({options.view_outlier:g} x the median view)")
        remaining -= 1
        changed = True
    return changed


def coverage(views: list[FrameDetection], image_size: tuple[int, int], bins: tuple[int, int] = (8, 6)) -> float:
    """Fraction of the cells of a ``bins`` grid over the image that hold at least one of the views' corners."""
    width, height = image_size
    corners = np.concatenate([v.corners for v in views]) if views else np.zeros((0, 2))
    counts, _, _ = np.histogram2d(corners[:, 0], corners[:, 1], bins=bins, range=[[-0.5, width - 0.5], [-0.5, height - 0.5]])
    return float((counts > 0).mean())


# A model that folds back this far out or farther (as a share of the way to the image's farthest corner) is kept,
# with a note: only the corners' tips are lost. Nearer in, k3 is fixed at 0 and the camera solved again, or the
# calibration refused. Set by geometry, then checked on real cameras: caliscope's own four webcam calibrations and
# OpenCV's tutorial camera do not fold; the deep detector's calibration of caliscope's cam_1 folds at 97 %, and
# OpenCV's corners of a damaged copy of it gave k3 = -0.42, a fold at 81 % (the k3 = -1.20: 65 %).
MIN_FOLD_SHARE = 0.9


def fold_share(camera: Camera, samples: int = 20000) -> float | None:
    """Where a pinhole camera's radial distortion stops growing with the radius before it reaches the image's
    farthest corner, as a share of that corner's (distorted, normalised) radius; None when the mapping increases
    all the way there, as a lens's does (mrcal flags such models too). A fold means two radii image to one and the
    pixels beyond cannot be undistorted: a k3 solved from views that leave the image's corners empty can do this
    (seen on a real 1280x720 webcam: k3 = -1.20, a fold at normalised radius 0.57). Fisheye models: None."""
    if camera.model == "fisheye":
        return None
    k1, k2, _, _, k3, k4, k5, k6 = np.pad(camera.dist, (0, max(0, 8 - camera.dist.size)))[:8]
    (fx, _, cx), (_, fy, cy), _ = camera.K
    width, height = camera.image_size
    corners = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [-0.5, height - 0.5], [width - 0.5, height - 0.5]])
    reach = float(np.max(np.hypot((corners[:, 0] - cx) / fx, (corners[:, 1] - cy) / fy)))
    r = np.linspace(0.0, 5.0 * reach, samples)  # undistorted radii; barrel distortion needs them beyond the reach
    r2 = r * r
    distorted = r * (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    falling = np.flatnonzero(np.diff(distorted) <= 0)
    upto = distorted if len(falling) == 0 else distorted[:falling[0] + 1]
    if np.any(upto >= reach):
        return None
    return float(upto.max() / reach)


def _coverage_notes(views: list[FrameDetection], image_size: tuple[int, int]) -> list[str]:
    share = coverage(views, image_size)
    if share >= MIN_COVERAGE:
        return []
    return [f"the corners cover only {100 * share:.0f} % of the image (8 x 6 cells): the distortion beyond them is "
            f"extrapolated; capture the board near the image's edges and corners too"]


def _check_solution(solution: _Solution, model: str, image_size: tuple[int, int]) -> None:
    K = solution.K
    if not np.all(np.isfinite(K)) or not np.all(np.isfinite(solution.dist)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CalibrationError(f"the {model} calibration diverged: capture more views covering the whole image at varied tilts")
    for name in ("fx", "fy"):
        deviation = solution.std.get(name)
        value = K[0, 0] if name == "fx" else K[1, 1]
        if deviation is not None and deviation > MAX_RELATIVE_STD * value:
            raise CalibrationError(
                f"{name} = {value:.1f} +- {deviation:.1f} px is too uncertain (> {100 * MAX_RELATIVE_STD:.0f} %): the views "
                f"do not pin the focal length down; capture the board tilted 20-40 degrees in several directions, near "
                f"the image's edges and corners too")
