"""One solve of a camera model from views' corners: OpenCV's ``calibrateCameraExtended`` for the ``pinhole`` and
``rational`` models (with the parameters' deviations), ``cv2.fisheye.calibrate`` for ``fisheye`` (step 3 of
`intrinsics`), and the residuals of a solution.

object_points[v]: (N_v, 3) board points (metres), image_points[v]: (N_v, 2) pixels (OpenCV's convention).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from deepcharuco.calibration.views import CalibrationError
from deepcharuco.core.errors import OptionError
from deepcharuco.core.opencv_api import fisheye_calibration_flags, fisheye_flag


MODELS = ("pinhole", "rational", "fisheye")


# The first stage of every pinhole and rational calibration: k3 (and k4..k6) at 0. Outliers are judged
# under this model first: one that can bend its edges with k3 bends them to meet a wrong corner there
# (a corner the deep detector put 17 px off, at the image's edge, took a free-k3 solve to fx 0.7 % and
# cy 4 px off the rendered truth; judged under the stiff model it was dropped and the lens recovered).
STIFF = ("pinhole", True)


# Names of calibrateCameraExtended's 18 intrinsic standard deviations, in its order.
STD_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4", "tau_x", "tau_y")


# ----------------------------------------------------------------------------------------- solving
@dataclass
class Solution:
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
          model: str, fix_k3: bool = False, guess: Solution | None = None, zero_tangent: bool = False) -> Solution:
    """One solve of OpenCV's calibration. object_points[v]: (N_v, 3), image_points[v]: (N_v, 2).
    ``fix_k3``: keep k3 at 0 (pinhole and rational models). ``guess``: a solution to start from
    (pinhole and rational models). ``zero_tangent``: keep p1 and p2 at 0 (pinhole and rational).

    Without a guess, a model with k3 (or k4..k6) free is solved in two stages: first with them held
    at 0 (`STIFF`), then free from there. Started from no distortion at all, OpenCV's
    Levenberg-Marquardt can settle where k2 and k3 cancel each other."""
    try:
        if model == "fisheye":
            return _solve_fisheye(object_points, image_points, image_size, guess)
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


def intrinsic_names(model: str) -> tuple[str, ...]:
    """The pinhole or rational model's intrinsics in `STD_NAMES` order: fx fy cx cy and its distortion terms."""
    return STD_NAMES[:4 + (5 if model == "pinhole" else 8)]


def _named(raw: tuple, model: str, fix_k3: bool, zero_tangent: bool = False) -> Solution:
    K, dist, rvecs, tvecs, std_intrinsics, _ = raw
    names = intrinsic_names(model)
    count = len(names) - 4
    std = {name: float(v) for name, v in zip(names, std_intrinsics[:len(names)])
           if not (fix_k3 and name == "k3") and not (zero_tangent and name in ("p1", "p2"))
           and not (v == 0.0 and name in ("k3", "k4", "k5", "k6"))}
    return Solution(K=np.asarray(K, np.float64), dist=dist[:count].copy(),
                     rvecs=np.asarray(rvecs, np.float64).reshape(-1, 3), tvecs=np.asarray(tvecs, np.float64).reshape(-1, 3),
                     std=std)


def _solve_fisheye(object_points: list[np.ndarray], image_points: list[np.ndarray],
                   image_size: tuple[int, int], guess: Solution | None = None) -> Solution:
    """``cv2.fisheye.calibrate`` from ``guess``, or without one in two stages, as the pinhole model's `STIFF`: k1..k4
    held at 0 (the equidistant lens), then free from there (the better of the two by RMS). Started with k1..k4
    free from OpenCV's own guess (f = max(width, height) / pi), a drawn 180 degree lens (f 223 px at 1024 x 768)
    settled at RMS 40-800 px or failed ("norm_u1 > 0") on 10-30 views; in two stages it came within 0.1 px of fx."""
    # (1, N, 3) and (1, N, 2): OpenCV 5's fisheye calibration fails on OpenCV 4's (N, 1, 3) with "Sizes of input
    # arguments do not match"; both take these
    objects = [p.reshape(1, -1, 3).astype(np.float64) for p in object_points]
    images = [p.reshape(1, -1, 2).astype(np.float64) for p in image_points]
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-10)
    flags = fisheye_calibration_flags()
    first = None
    if guess is None:
        stiff = flags | fisheye_flag("FIX_K1") | fisheye_flag("FIX_K2") | fisheye_flag("FIX_K3") | fisheye_flag("FIX_K4")
        first = cv2.fisheye.calibrate(objects, images, image_size, None, np.zeros(4), flags=stiff, criteria=criteria)
        K, dist = first[1], first[2]
    else:
        K, dist = guess.K.copy(), guess.dist.copy()
    try:
        rms, K, dist, rvecs, tvecs = cv2.fisheye.calibrate(objects, images, image_size, K.copy(), dist.copy(),
                                                           flags=flags | fisheye_flag("USE_INTRINSIC_GUESS"),
                                                           criteria=criteria)
    except cv2.error:
        if first is None:
            raise
        rms = math.inf
    if first is not None and not rms <= first[0] + 1e-9:
        rms, K, dist, rvecs, tvecs = first
    return Solution(K=np.asarray(K, np.float64), dist=np.asarray(dist, np.float64).ravel(),
                     rvecs=np.asarray(rvecs, np.float64).reshape(-1, 3), tvecs=np.asarray(tvecs, np.float64).reshape(-1, 3),
                     std={})


# cv2.fisheye.calibrate starts every view's pose afresh at each step from its corners undistorted onto the plane
# z = 1 (InitExtrinsics: a homography), which fails ("norm_u1 > 0") or settles off on corners near 90 degrees off the
# axis, where that plane lies at infinity: with the deep detector's corners of drawn 180 degree lenses (it finds more
# of them near the rim than OpenCV's) one camera's solve failed and another's put the rig's pairs 5 degrees apart.
# One camera's fisheye calibration leaves out the corners beyond this angle under a first solve (`fisheye_start`);
# a rig's bundle adjustment uses them all (`calibration.rig`).
FISHEYE_MAX_DEG = 80.0


def fisheye_start(object_points: list[np.ndarray], image_points: list[np.ndarray], image_size: tuple[int, int]
                  ) -> Solution:
    """A first fisheye solve (`_solve_fisheye`) from all views, or where OpenCV fails, from the innermost half,
    quarter, ... of them by the reach of their farthest corner from the image's centre (at least 3 views)."""
    centre = (np.asarray(image_size, np.float64) - 1) / 2
    order = np.argsort([np.linalg.norm(p - centre, axis=1).max() for p in image_points], kind="stable")
    count, failure = len(order), "no views"
    while count >= 3:
        chosen = sorted(order[:count])
        try:
            return _solve_fisheye([object_points[i] for i in chosen], [image_points[i] for i in chosen], image_size)
        except cv2.error as exc:
            failure = str(exc).strip().splitlines()[-1]
        count //= 2
    raise CalibrationError(f"OpenCV's fisheye calibration failed ({failure}), even from the views nearest the image's "
                           f"centre: capture more views of the board, at varied tilts, in the middle of the image too")


def beyond_fisheye_reach(image_points: list[np.ndarray], solution: Solution) -> list[np.ndarray]:
    """Per view, (N_v,) bool: the corners more than `FISHEYE_MAX_DEG` off the axis of the fisheye ``solution``, or
    beyond the angle where its distorted angle theta_d stops growing, whichever comes first (a corner's distance
    from the axis on the normalised image plane against theta_d there). A solve of a narrow lens puts its terms where
    its corners are: past them theta_d may turn down and go negative by 80 degrees (k4 = -0.6 on a 63 degree lens),
    which left every corner "beyond" and no view to calibrate."""
    k1, k2, k3, k4 = solution.dist
    angles = np.linspace(0.0, math.radians(FISHEYE_MAX_DEG), 801)
    theta_d = angles * (1 + k1 * angles ** 2 + k2 * angles ** 4 + k3 * angles ** 6 + k4 * angles ** 8)
    growing = np.diff(theta_d) > 0
    limit = theta_d[len(growing) if growing.all() else int(np.argmin(growing))]  # up to the first step not growing
    K = solution.K
    out = []
    for pixels in image_points:
        y = (pixels[:, 1] - K[1, 2]) / K[1, 1]
        x = (pixels[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
        out.append(np.hypot(x, y) > limit)
    return out


def reproject(object_points: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, K: np.ndarray, dist: np.ndarray,
              model: str) -> np.ndarray:
    """(N, 2) pixels of the (N, 3) board points under a pose and intrinsics of ``model``."""
    if model == "fisheye":
        points, _ = cv2.fisheye.projectPoints(object_points.reshape(-1, 1, 3), rvec.reshape(3, 1),
                                              tvec.reshape(3, 1), K, dist)
    else:
        points, _ = cv2.projectPoints(object_points, rvec, tvec, K, dist)
    return points.reshape(-1, 2)


def residuals_of(object_points: list[np.ndarray], image_points: list[np.ndarray], solution: Solution, model: str
               ) -> tuple[list[np.ndarray], list[np.ndarray], float, np.ndarray]:
    """Each view's residuals (N_v, 2) (detected minus reprojected, px), their norms (N_v,), the RMS over all
    corners and each view's RMS (V,)."""
    residuals = [image - reproject(points, r, t, solution.K, solution.dist, model)
                 for points, image, r, t in zip(object_points, image_points, solution.rvecs, solution.tvecs)]
    norms = [np.linalg.norm(r, axis=1) for r in residuals]
    rms = float(np.sqrt(np.mean(np.concatenate(norms) ** 2)))
    return residuals, norms, rms, np.array([math.sqrt(float(np.mean(n ** 2))) for n in norms])
