"""Which distortion terms the views support, and how certain the solved parameters are (steps 5 and 7 of
`intrinsics`): `select_terms` holds p1 p2 at 0 where views held out of the fit are predicted as well without them
(cross-validation over views); `bootstrap_std` resamples the views to give each parameter a deviation no smaller
than the spread the views themselves show.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from deepcharuco.calibration.solve import Solution, _flags, _held, intrinsic_names


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
                 model: str, fix_k3: bool, solution: Solution, folds: int = SELECTION_FOLDS
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
                  model: str, terms: str, solution: "Solution", rounds: int = BOOTSTRAP_ROUNDS, seed: int = 0
                  ) -> dict[str, float]:
    """{name: standard deviation} of the pinhole or rational intrinsics ``terms`` solves (`terms_name`), over
    ``rounds`` OpenCV solves of views drawn with replacement, each started from ``solution`` (seeded: the same
    views give the same deviations)."""
    names = [n for n in intrinsic_names(model) if n in ("fx", "fy", "cx", "cy") or n in terms.split()]
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
        everything = dict(zip(intrinsic_names(model), [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist]))
        values.append([everything[name] for name in names])
    if len(values) < rounds // 2:
        return {}
    return dict(zip(names, (float(v) for v in np.std(np.array(values), axis=0, ddof=1))))
