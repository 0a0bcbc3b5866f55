"""The rig's bundle adjustment (steps 5-6 of `rig`): ``scipy.optimize.least_squares`` with a sparse Jacobian over
the cameras' free intrinsics, their poses and every (instant, board)'s pose (`bundle_adjust`; in closed form,
`rig_jacobian`, finite differences where a camera is a fisheye), each corner weighed by
its detector's covariance and its view's excess (`corner_weights`), and the parameters' deviations from the
Gauss-Newton covariance or the instants' cluster-robust estimate (`parameter_deviations`).
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from threadpoolctl import threadpool_limits

from deepcharuco.boards.board import BoardSpec
from deepcharuco.calibration.rig_jacobian import residual_jacobian
from deepcharuco.calibration.rig_model import INTRINSICS, RigView, project, rotations_from_vectors
from deepcharuco.calibration.weighting import view_excess


HUBER_PX = 1.0  # residuals beyond this count linearly in the bundle adjustment


# least_squares' sparse trust-region steps come from LSMR; at its default tolerances (1e-6) a 3-camera problem took
# 200+ steps and stopped short (fx 2 % off its start moved back only half way); at 1e-12 it converges in ~50.
MAX_STEPS = 300
# FISHEYE_STEPS: with a fisheye camera in the rig the sparse (LSMR) steps stalled at the minimum without meeting the
# tolerances: a drawn 3-camera fisheye rig (14 instants, OpenCV's corners) ran all 300 steps twice (~200 s on 2 busy
# cores) where exact (dense) steps stopped after 10 at the same cost (42.2487). Its Jacobian is dense below this many
# entries (~100 MB); above, the sparse steps as for pinhole rigs.
MAX_DENSE_ENTRIES = 12_000_000
MIN_VARIANCE_PX2 = 1e-8  # added to every corner's covariance: a degenerate one must not weigh infinitely


# ----------------------------------------------------------------------------------------- bundle adjustment
@dataclass
class _Problem:
    """The bundle adjustment's layout: which parameters are free and where each observation's come from."""

    start: np.ndarray  # (C, 12) intrinsics
    free: np.ndarray  # (C, 12) bool
    instants: list[tuple[int, int]]  # board pose k is of instants[k] = (instant, board)
    camera: np.ndarray  # (M,) per observed corner
    pose: np.ndarray  # (M,) index into instants
    points: np.ndarray  # (M, 3) board points
    observed: np.ndarray  # (M, 2)
    # (C, 12) each starting intrinsic's prior standard deviation per px of corner noise (inf: no prior; `PRIOR_NOTE`)
    prior: np.ndarray | None = None
    # (M, 2, 2) each corner's weight's root L (its residual counts as L r; L^T L its information, `corner_weights`),
    # None: every corner alike
    roots: np.ndarray | None = None
    fisheye: np.ndarray | None = None  # (C,) bool: the cameras of OpenCV's fisheye model (None: none)

    @property
    def prior_sigma(self) -> np.ndarray:
        """(free parameters,) the prior's standard deviation of each free intrinsic per px of noise (inf: none)."""
        return np.full(self.n_intrinsics, np.inf) if self.prior is None else self.prior[self.free]

    @property
    def n_cameras(self) -> int:
        return len(self.start)

    @property
    def n_intrinsics(self) -> int:
        return int(self.free.sum())

    @property
    def n_global(self) -> int:
        return self.n_intrinsics + 6 * (self.n_cameras - 1)

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        intrinsics = self.start.copy()
        intrinsics[self.free] = x[:self.n_intrinsics]
        cameras = np.concatenate([np.zeros((1, 6)), x[self.n_intrinsics:self.n_global].reshape(-1, 6)])
        boards = x[self.n_global:].reshape(-1, 6)
        return intrinsics, cameras, boards

    def residuals(self, x: np.ndarray) -> np.ndarray:
        intrinsics, cameras, boards = self.unpack(x)
        R_b, R_c = rotations_from_vectors(boards[:, :3]), rotations_from_vectors(cameras[:, :3])
        in_rig = np.einsum("mij,mj->mi", R_b[self.pose], self.points) + boards[self.pose, 3:]
        in_camera = np.einsum("mij,mj->mi", R_c[self.camera], in_rig) + cameras[self.camera, 3:]
        fisheye = None if self.fisheye is None else self.fisheye[self.camera]
        pixels = project(in_camera, intrinsics[self.camera], fisheye) - self.observed
        if self.roots is not None:
            pixels = np.einsum("mij,mj->mi", self.roots, pixels)
        pixels = pixels.ravel()
        sigma = self.prior_sigma
        held = np.isfinite(sigma)
        if not held.any():
            return pixels
        return np.concatenate([pixels, (x[:self.n_intrinsics][held] - self.start[self.free][held]) / sigma[held]])

    def sparsity(self) -> coo_matrix:
        """Which parameters each residual depends on: its camera's free intrinsics and pose, its instant's board pose."""
        offsets = np.concatenate([[0], np.cumsum(self.free.sum(1))])
        rows, columns = [], []
        for m, (camera, pose) in enumerate(zip(self.camera, self.pose)):
            mine = list(range(offsets[camera], offsets[camera + 1]))
            if camera > 0:
                mine += range(self.n_intrinsics + 6 * (camera - 1), self.n_intrinsics + 6 * camera)
            mine += range(self.n_global + 6 * pose, self.n_global + 6 * pose + 6)
            rows += [2 * m] * len(mine) + [2 * m + 1] * len(mine)
            columns += mine * 2
        held = np.flatnonzero(np.isfinite(self.prior_sigma))
        rows += list(2 * len(self.camera) + np.arange(len(held)))
        columns += list(held)
        shape = (2 * len(self.camera) + len(held), self.n_global + 6 * len(self.instants))
        return coo_matrix((np.ones(len(rows), np.int8), (rows, columns)), shape=shape)


def _vectors(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return np.concatenate([cv2.Rodrigues(R)[0].ravel(), t])


def bundle_adjust(views: list[RigView], boards: list[BoardSpec], intrinsics: np.ndarray, free: np.ndarray,
                  rotations: np.ndarray, translations: np.ndarray,
                  board_poses: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]], prior: np.ndarray | None = None,
                  prior_start: np.ndarray | None = None, weights: list[np.ndarray] | None = None,
                  fisheye: np.ndarray | None = None):
    """One robust solve from the given start (board poses {(instant, board): (R (3, 3), t)}); ``fisheye`` (C,) bool:
    the cameras of OpenCV's fisheye model (`rig_model.project_fisheye`; None: none); ``prior`` (C, 12): the
    intrinsics' prior deviations per px of noise about ``prior_start`` (default: ``intrinsics``); ``weights``: per
    view, (N, 2, 2) each corner's information (`corner_weights`; None: all alike). Returns (intrinsics (C, 12),
    rotations (C, 3, 3), translations (C, 3), board poses {(instant, board): (rvec, tvec)}, per-view residuals (px,
    unweighted), the global parameters' covariance (scaled) and the layout)."""
    instants = sorted(board_poses)
    index = {key: k for k, key in enumerate(instants)}
    objects = [board.object_points() for board in boards]
    problem = _Problem(
        start=(intrinsics if prior_start is None else prior_start).copy(), free=free.copy(), instants=instants,
        camera=np.concatenate([np.full(len(v.ids), v.camera) for v in views]),
        pose=np.concatenate([np.full(len(v.ids), index[v.key]) for v in views]),
        points=np.concatenate([objects[v.board][v.ids] for v in views]),
        observed=np.concatenate([v.corners for v in views]), prior=prior,
        roots=None if weights is None else np.swapaxes(np.linalg.cholesky(np.concatenate(weights)), -1, -2),
        fisheye=None if fisheye is None else np.asarray(fisheye, bool))
    x0 = np.concatenate([intrinsics[free],
                         np.concatenate([_vectors(rotations[c], translations[c]) for c in range(1, len(intrinsics))])
                         if len(intrinsics) > 1 else np.zeros(0),
                         np.concatenate([_vectors(*board_poses[i]) for i in instants])])
    rows = 2 * len(problem.camera) + int(np.isfinite(problem.prior_sigma).sum())
    dense = problem.fisheye is not None and problem.fisheye.any() and rows * len(x0) <= MAX_DENSE_ENTRIES
    if dense:
        solver = {"tr_solver": "exact", "jac": _dense_jacobian(problem)}  # FISHEYE_STEPS
    elif problem.fisheye is not None and problem.fisheye.any():
        solver = {"jac_sparsity": problem.sparsity(), "tr_options": {"atol": 1e-12, "btol": 1e-12}}
    else:  # the Jacobian in closed form: one pass, where finite differences took a few dozen residual evaluations
        solver = {"jac": lambda x: residual_jacobian(problem, x), "tr_options": {"atol": 1e-12, "btol": 1e-12}}
    # The dense steps' SVDs on one BLAS thread: on 2 busy cores OpenBLAS's two spinning threads took 4 s for one SVD of
    # a 2300 x 184 Jacobian that one thread does in 0.26 s.
    with threadpool_limits(limits=1, user_api="blas") if dense else contextlib.nullcontext():
        solution = least_squares(problem.residuals, x0, method="trf", loss="huber", f_scale=HUBER_PX, x_scale="jac",
                                 xtol=1e-10, ftol=1e-10, gtol=1e-10, max_nfev=MAX_STEPS, **solver)
    solved, cameras, boards = problem.unpack(solution.x)
    flat = solution.fun[:2 * len(problem.camera)].reshape(-1, 2)  # least_squares' fun: not weighed by the loss
    if problem.roots is not None:  # back to pixels: L r = f
        flat = np.linalg.solve(problem.roots, flat[..., None])[..., 0]
    residuals, start = [], 0
    for v in views:
        residuals.append(flat[start:start + len(v.ids)])
        start += len(v.ids)
    R_c = rotations_from_vectors(cameras[:, :3])
    covariance = _global_covariance(problem, solution, flat)
    poses = {key: (boards[k, :3].copy(), boards[k, 3:].copy()) for k, key in enumerate(instants)}
    return solved, R_c, cameras[:, 3:].copy(), poses, residuals, covariance, problem


def _dense_jacobian(problem: _Problem):
    """The residuals' Jacobian as a dense array, by the finite differences ``least_squares`` takes with
    ``jac_sparsity`` (columns that share no residual perturbed together: a few dozen evaluations, not one per
    parameter); scipy's dense "2-point" differences where its grouping is not importable."""
    try:
        from scipy.optimize._numdiff import approx_derivative, group_columns
    except ImportError:  # a scipy that moved them: every column on its own (slower, the same steps)
        return "2-point"
    structure = problem.sparsity().tocsc()
    groups = group_columns(structure)

    def jacobian(x: np.ndarray) -> np.ndarray:
        return approx_derivative(problem.residuals, x, method="2-point", sparsity=(structure, groups)).toarray()

    return jacobian


def _global_covariance(problem: _Problem, solution, flat: np.ndarray) -> np.ndarray:
    """Covariance of the intrinsics and camera poses, each instant's board pose eliminated (Schur complement S of
    the Gauss-Newton matrix J^T J; J as the Huber loss weighs it, so rows beyond `HUBER_PX` count for ~nothing).
    Two estimates, and per
    parameter the larger variance:

    - the model's, S^-1 sigma^2 with sigma^2 = sum r^2 / (2N - parameters): right when every corner's error is
      independent (exact projections plus noise: errors / deviations spread 1.0-1.2 in `tests/calibration/test_rig.py`);
    - the instants' (a cluster-robust "sandwich", S^-1 (sum_k u_k u_k^T) S^-1 K / (K - 1), u_k instant k's share of
      the gradient with its board pose eliminated): right when a view's corners err together (a detector's bias at
      one tilt, motion blur along one direction), which the model's estimate counts as independent and understates.
    """
    J = solution.jac.tocsr() if hasattr(solution.jac, "tocsr") else np.asarray(solution.jac)
    # The plain residuals (least_squares' fun is not weighed by the loss): an outlier's row of J is ~0, so it adds
    # nothing to the instants' estimate, but its residual does enter the model's variance (which errs large).
    residual = solution.fun
    g = problem.n_global
    corners = 2 * len(problem.camera)  # the rows after these are the intrinsics' prior, one cluster of its own
    rows = np.repeat(problem.pose, 2)  # each corner's two residuals belong to its instant
    order = np.argsort(rows, kind="stable")
    bounds = np.searchsorted(rows[order], np.arange(len(problem.instants) + 1))
    A = np.zeros((g, g))
    pieces = []
    for k in range(len(problem.instants)):
        mine = order[bounds[k]:bounds[k + 1]]
        block = J[mine]
        block = block.toarray() if hasattr(block, "toarray") else block
        J_g, J_b, r = block[:, :g], block[:, g + 6 * k:g + 6 * k + 6], residual[mine]
        B = J_g.T @ J_b
        C_inverse = np.linalg.pinv(J_b.T @ J_b)
        A += J_g.T @ J_g - B @ C_inverse @ B.T
        pieces.append(J_g.T @ r - B @ (C_inverse @ (J_b.T @ r)))
    if J.shape[0] > corners:
        J_p = J[corners:, :g]
        J_p = J_p.toarray() if hasattr(J_p, "toarray") else J_p
        A += J_p.T @ J_p
        pieces.append(J_p.T @ residual[corners:])
    S_inverse = np.linalg.pinv(A)
    freedom = J.shape[0] - J.shape[1]
    variance = float(np.sum(residual ** 2)) / freedom if freedom > 0 else math.nan
    model = S_inverse * variance
    count = len(pieces)
    gradient = np.stack(pieces)
    robust = S_inverse @ (gradient.T @ gradient) @ S_inverse * (count / max(count - 1, 1))
    larger = np.sqrt(np.maximum(np.diag(model), np.diag(robust)) / np.maximum(np.diag(model), 1e-300))
    return model * np.outer(larger, larger)


def parameter_deviations(problem: _Problem, covariance: np.ndarray, names: list[str]) -> list[dict[str, float]]:
    diagonal = np.sqrt(np.maximum(np.diag(covariance), 0.0))
    std = [dict() for _ in range(problem.n_cameras)]
    position = 0
    for c in range(problem.n_cameras):
        for p, name in enumerate(INTRINSICS):
            if problem.free[c, p]:
                std[c][name] = float(diagonal[position])
                position += 1
    for c in range(1, problem.n_cameras):
        block = diagonal[position:position + 6]
        std[c]["rotation_deg"] = float(np.degrees(block[:3].max()))
        std[c]["tx"], std[c]["ty"], std[c]["tz"] = (float(v) for v in block[3:])
        position += 6
    return std


# ----------------------------------------------------------------------------------------- corner weights
def corner_weights(views: list[RigView], residuals: list[np.ndarray] | None = None) -> list[np.ndarray]:
    """Per view, (N, 2, 2) each corner's information for the bundle adjustment: the inverse of its detector's
    covariance plus its view's excess, the part of the view's residual covariance (``residuals``: per view, (N, 2)
    px from the last solve; None: no excess yet) that its corners' covariances do not explain (a motion the detector
    did not see, a board's flex), as `calibration.weigh_views` weighs one camera's corners. All are scaled by one
    number, the median corner's variance, so that a typical corner weighs ~1 and the solve's Huber scale
    (`HUBER_PX`), the prior's unit and the outlier limits stay in pixels."""
    totals = []
    for k, view in enumerate(views):
        covariances = view.covariances
        if residuals is not None and len(residuals[k]) >= 4:
            covariances = covariances + view_excess(residuals[k], covariances)
        totals.append(covariances + MIN_VARIANCE_PX2 * np.eye(2))
    scale = float(np.median(np.trace(np.concatenate(totals), axis1=1, axis2=2))) / 2
    return [scale * np.linalg.inv(total) for total in totals]


# ----------------------------------------------------------------------------------------- the whole solve
def free_mask(terms: str | None, slots: tuple[str, ...]) -> np.ndarray:
    """(12,) which `INTRINSICS` are solved: fx fy cx cy and the named distortion ``terms`` (e.g. "k1 k2 k3") among
    the camera's own coefficients ``slots`` (`rig_model.distortion_names`); None: nothing (intrinsics held as
    given)."""
    if terms is None:
        return np.zeros(12, bool)
    names = (set(terms.split()) & set(slots)) | {"fx", "fy", "cx", "cy"}
    return np.array([name in names for name in INTRINSICS])
