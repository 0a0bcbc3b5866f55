"""Views and corners weighed by how well they are measured (step 6 of `intrinsics`): `weigh_views` refits the
camera with each view weighed by the spread of its own residuals, or each corner by its detector's covariance plus
its view's unexplained excess (`view_excess`); `weighted_solve` is the weighted Levenberg-Marquardt over the
intrinsics and every view's pose (OpenCV's calibration takes no weights).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from deepcharuco.calibration.solve import STD_NAMES, Solution, intrinsic_names, residuals_of
from deepcharuco.calibration.views import VIEW_WEIGHT_SPREAD
from deepcharuco.core.blas import single_threaded_blas


# ----------------------------------------------------------------------------------------- view weights
# Each view's corners are weighed by the spread of its own residuals (`weigh_views`; VIEW_WEIGHT_SPREAD above).
# Re-weigh from each weighted solution's residuals this many times (IRLS): on the 6 validation shake videos of seeds
# 0 and 3, 4 rounds give what 8 do to 0.001 % of fx (1 round: within 0.01 % and 0.12 px of it).
WEIGHT_ROUNDS = 4


# Fewer views: all weigh alike (the median view says too little of what a normal view is); the same floor as
# `select_terms`' (not tuned: every validation sequence has 21 views or more).
MIN_WEIGHTED_VIEWS = 10
LM_STEPS = 50  # Levenberg-Marquardt steps of one weighted solve (from OpenCV's solution; it stops when the cost settles)


def weigh_views(object_points: list[np.ndarray], image_points: list[np.ndarray], solution: Solution, model: str,
                terms: str, spread: float = VIEW_WEIGHT_SPREAD, rounds: int = WEIGHT_ROUNDS,
                corner_covariances: list[np.ndarray] | None = None) -> tuple[Solution, np.ndarray]:
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
    names = intrinsic_names(model)
    free = np.array([n in ("fx", "fy", "cx", "cy") or n in terms.split() for n in names])
    with single_threaded_blas():  # many small inverses and products (`core.blas` says why)
        if corner_covariances is not None:
            return _weigh_corners(object_points, image_points, solution, model, free, corner_covariances, rounds)
        return _weigh_views(object_points, image_points, solution, model, free, spread, rounds)


def _weigh_views(object_points: list[np.ndarray], image_points: list[np.ndarray], solution: Solution, model: str,
                 free: np.ndarray, spread: float, rounds: int) -> tuple[Solution, np.ndarray]:
    """`weigh_views` with each view's residuals' spread (its docstring)."""
    current = solution
    information = [np.eye(2)] * len(object_points)
    for _ in range(rounds):
        residuals = residuals_of(object_points, image_points, current, model)[0]
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


def _weigh_corners(object_points: list[np.ndarray], image_points: list[np.ndarray], solution: Solution, model: str,
                   free: np.ndarray, corner_covariances: list[np.ndarray], rounds: int) -> tuple[Solution, np.ndarray]:
    """`weigh_views` with each corner's covariance (its docstring)."""
    current = solution
    information = [np.linalg.inv(c) for c in corner_covariances]
    for _ in range(rounds):
        residuals = residuals_of(object_points, image_points, current, model)[0]
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


def weighted_solve(object_points: list[np.ndarray], image_points: list[np.ndarray], start: Solution, free: np.ndarray,
                   information: list[np.ndarray]) -> Solution:
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
        """(U (c, c), g (c,), V (views, 6, 6), W (views, c, 6), gv (views, 6)): the intrinsics' block and gradient,
        and each view's pose block, cross block and pose gradient."""
        U = sum(j.T @ j for _, _, j in parts)
        g = sum(j.T @ r for r, _, j in parts)
        V = np.stack([p.T @ p for _, p, _ in parts])
        W = np.stack([j.T @ p for _, p, j in parts])
        gv = np.stack([p.T @ r for r, p, _ in parts])
        return U, g, V, W, gv

    current = cost(whitened(K, dist, rvecs, tvecs, False))
    damping = 1e-3
    diagonal = np.eye(6, dtype=bool)
    for _ in range(LM_STEPS):
        U, g, V, W, gv = normal_equations(whitened(K, dist, rvecs, tvecs, True))
        improved = False
        while damping < 1e8:
            # The poses eliminated (Schur complement), all views' 6 x 6 blocks inverted in one call.
            damped = V + damping * V * diagonal
            inverses = np.linalg.inv(damped)
            WV = W @ inverses  # (views, c, 6)
            reduced = U + damping * np.diag(np.diag(U)) - np.einsum("vij,vkj->ik", WV, W)
            rhs = -g + np.einsum("vij,vj->i", WV, gv)
            step = np.linalg.solve(reduced, rhs)
            full = np.zeros(len(free))
            full[free] = step
            K2 = K.copy()
            K2[0, 0] += full[0]
            K2[1, 1] += full[1]
            K2[0, 2] += full[2]
            K2[1, 2] += full[3]
            dist2 = dist + full[4:]
            poses = np.einsum("vij,vj->vi", inverses, -gv - np.einsum("vji,j->vi", W, step))
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
    U, g, V, W, gv = normal_equations(whitened(K, dist, rvecs, tvecs, True))
    U = U - np.einsum("vij,vkj->ik", W @ np.linalg.inv(V), W)
    measurements = 2 * sum(len(p) for p in objects)
    freedom = measurements - count - 6 * len(objects)
    scale = current / freedom if freedom > 0 else math.nan
    try:
        deviations = np.sqrt(np.maximum(np.diag(np.linalg.inv(U)), 0.0) * scale)
    except np.linalg.LinAlgError:
        deviations = np.full(count, math.nan)
    names = [n for n, f in zip(STD_NAMES, free) if f]
    return Solution(K=K, dist=dist, rvecs=rvecs, tvecs=tvecs, std=dict(zip(names, map(float, deviations))))
