"""The rig bundle adjustment's Jacobian in closed form (`bundle._Problem`'s residuals, OpenCV's pinhole and rational
models): one pass over the corners instead of the few dozen residual evaluations finite differences take, which
were most of a rig calibration's time.

A corner m of camera c seen at instant k: its camera-frame point P = R_c (R_b p + t_b) + t_c (the board pose's R_b
t_b, the camera's R_c t_c; camera 0 is the rig's frame and has no pose parameters), its residual L (pixel(P) -
observed) (L: the corner's weight's root, identity without weights). The pixel's derivatives: by the intrinsics
and by P (`pinhole_derivatives`), P's by each rotation vector (`rotation_derivatives`, Gallego and Yezzi's closed
form), chained. Fisheye cameras are not derived here: `bundle` takes finite differences where the rig has one.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix, csr_matrix

from deepcharuco.calibration.rig_model import cross_matrices, rotations_from_vectors

SMALL_ANGLE = 1e-8  # below this rotation angle (rad) dR/dw is the cross-product matrix of the axis (its limit at 0)


def rotation_derivatives(rvecs: np.ndarray) -> np.ndarray:
    """(K, 3) rotation vectors -> (K, 3, 3, 3): [k, i] the derivative of the rotation matrix (`rotations_from_vectors`)
    by the vector's i-th component: (v_i [v]x + [v x (I - R) e_i]x) R / |v|^2 (G. Gallego, A. Yezzi, "A compact
    formula for the derivative of a 3-D rotation in exponential coordinates", 2015); [e_i]x at |v| ~ 0."""
    v = np.asarray(rvecs, np.float64).reshape(-1, 3)
    R = rotations_from_vectors(v)
    squared = np.einsum("ki,ki->k", v, v)
    out = np.empty((len(v), 3, 3, 3))
    identity = np.eye(3)
    vx = cross_matrices(v)
    small = squared < SMALL_ANGLE ** 2
    for i in range(3):
        column = np.einsum("kab,b->ka", identity - R, identity[i])  # (I - R) e_i
        inner = v[:, i, None, None] * vx + cross_matrices(np.cross(v, column))
        out[:, i] = inner @ R / np.where(small, 1.0, squared)[:, None, None]
        out[small, i] = cross_matrices(identity[i][None])[0]
    return out


def pinhole_derivatives(points_cam: np.ndarray, intrinsics: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M, 3) camera-frame points, (M, 12) intrinsics (`rig_model.INTRINSICS` order) -> (d pixel / d point (M, 2, 3),
    d pixel / d intrinsics (M, 2, 12)) of `rig_model.project`'s pinhole (rational) model."""
    fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6 = intrinsics.T
    X, Y, Z = points_cam.T
    x, y = X / Z, Y / Z
    r2 = x * x + y * y
    numerator = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    denominator = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    radial = numerator / denominator
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    # d radial / d r2
    radial_r2 = ((k1 + r2 * (2 * k2 + 3 * r2 * k3)) * denominator
                 - numerator * (k4 + r2 * (2 * k5 + 3 * r2 * k6))) / (denominator * denominator)
    dxd_dx = radial + 2 * x * x * radial_r2 + 2 * p1 * y + 6 * p2 * x
    dxd_dy = 2 * x * y * radial_r2 + 2 * p1 * x + 2 * p2 * y
    dyd_dx = 2 * x * y * radial_r2 + 2 * p1 * x + 2 * p2 * y
    dyd_dy = radial + 2 * y * y * radial_r2 + 6 * p1 * y + 2 * p2 * x
    d_normalised = np.empty((len(X), 2, 2))  # d (u, v) / d (x, y)
    d_normalised[:, 0, 0], d_normalised[:, 0, 1] = fx * dxd_dx, fx * dxd_dy
    d_normalised[:, 1, 0], d_normalised[:, 1, 1] = fy * dyd_dx, fy * dyd_dy
    d_xy = np.zeros((len(X), 2, 3))  # d (x, y) / d (X, Y, Z)
    d_xy[:, 0, 0], d_xy[:, 0, 2] = 1 / Z, -x / Z
    d_xy[:, 1, 1], d_xy[:, 1, 2] = 1 / Z, -y / Z
    d_point = d_normalised @ d_xy
    d_intrinsics = np.zeros((len(X), 2, 12))
    d_intrinsics[:, 0, 0], d_intrinsics[:, 1, 1] = xd, yd
    d_intrinsics[:, 0, 2], d_intrinsics[:, 1, 3] = 1.0, 1.0
    powers = (r2, r2 * r2, r2 * r2 * r2)
    for slot, power in zip((4, 5, 8), powers):  # k1 k2 k3: the numerator
        d_intrinsics[:, 0, slot], d_intrinsics[:, 1, slot] = fx * x * power / denominator, fy * y * power / denominator
    for slot, power in zip((9, 10, 11), powers):  # k4 k5 k6: the denominator
        scale = -radial * power / denominator
        d_intrinsics[:, 0, slot], d_intrinsics[:, 1, slot] = fx * x * scale, fy * y * scale
    d_intrinsics[:, 0, 6], d_intrinsics[:, 1, 6] = fx * 2 * x * y, fy * (r2 + 2 * y * y)  # p1
    d_intrinsics[:, 0, 7], d_intrinsics[:, 1, 7] = fx * (r2 + 2 * x * x), fy * 2 * x * y  # p2
    return d_point, d_intrinsics


def residual_jacobian(problem, x: np.ndarray) -> csr_matrix:
    """The Jacobian of ``problem.residuals`` (a `bundle._Problem` without fisheye cameras) at ``x``: (rows, parameters)
    sparse, the pattern of ``problem.sparsity()``."""
    intrinsics, cameras, boards = problem.unpack(x)
    camera, pose, points = problem.camera, problem.pose, problem.points
    R_b, R_c = rotations_from_vectors(boards[:, :3]), rotations_from_vectors(cameras[:, :3])
    in_rig = np.einsum("mij,mj->mi", R_b[pose], points) + boards[pose, 3:]
    in_camera = np.einsum("mij,mj->mi", R_c[camera], in_rig) + cameras[camera, 3:]
    d_point, d_intrinsics = pinhole_derivatives(in_camera, intrinsics[camera])
    # d point / d (rotation vector, translation), of the camera's pose and of the board's
    d_camera = np.concatenate([np.einsum("mpij,mj->mip", rotation_derivatives(cameras[:, :3])[camera], in_rig),
                               np.broadcast_to(np.eye(3), (len(camera), 3, 3))], axis=2)
    d_board_rotation = np.einsum("mij,mpjk,mk->mip", R_c[camera], rotation_derivatives(boards[:, :3])[pose], points)
    d_board = np.concatenate([d_board_rotation, R_c[camera]], axis=2)
    blocks = {"camera": d_point @ d_camera, "board": d_point @ d_board, "intrinsics": d_intrinsics}  # (M, 2, *)
    if problem.roots is not None:
        blocks = {name: problem.roots @ block for name, block in blocks.items()}
    offsets = np.concatenate([[0], np.cumsum(problem.free.sum(1))])
    rows, columns, values = [], [], []
    pair = np.arange(len(camera))
    for c in range(problem.n_cameras):
        mine = pair[camera == c]
        if not len(mine):
            continue
        free = np.flatnonzero(problem.free[c])
        own = [(blocks["intrinsics"][mine][:, :, free], offsets[c] + np.arange(len(free)))]
        if c > 0:
            own.append((blocks["camera"][mine], problem.n_intrinsics + 6 * (c - 1) + np.arange(6)))
        for block, cols in own:
            rows.append(np.broadcast_to(2 * mine[:, None, None] + np.arange(2)[None, :, None], block.shape).ravel())
            columns.append(np.broadcast_to(cols[None, None, :], block.shape).ravel())
            values.append(block.ravel())
    board_columns = problem.n_global + 6 * pose[:, None] + np.arange(6)[None, :]  # (M, 6)
    rows.append(np.broadcast_to(2 * pair[:, None, None] + np.arange(2)[None, :, None], (len(pair), 2, 6)).ravel())
    columns.append(np.broadcast_to(board_columns[:, None, :], (len(pair), 2, 6)).ravel())
    values.append(blocks["board"].ravel())
    sigma = problem.prior_sigma
    held = np.flatnonzero(np.isfinite(sigma))
    rows.append(2 * len(camera) + np.arange(len(held)))
    columns.append(held)
    values.append(1.0 / sigma[held])
    shape = (2 * len(camera) + len(held), problem.n_global + 6 * len(problem.instants))
    return coo_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(columns))), shape=shape).tocsr()
