"""The rig's starting point (steps 1-3 of `rig`): each view's board pose in its camera (`view_poses`), each pair
of cameras' relative pose over the instants both see a board (`relative_poses`, with the spread that says whether
the videos are synchronised, `check_synchronised`), and the cameras chained from camera 0 along the best-shared
pairs (`chain_cameras`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from deepcharuco.boards.board import BoardSpec
from deepcharuco.calibration.rig_model import (Dropped, RigError, RigView, compose, intrinsic_vector, invert,
                                               project_fisheye, rotations_from_vectors)
from deepcharuco.geometry.camera import Camera
from deepcharuco.geometry.pose import MIN_SPREAD_RATIO


MAX_VIEW_POSE_PX = 4.0  # a view whose own PnP pose leaves an RMS above this is a misdetection or a wrong camera model
MIN_SHARED_VIEWS = 3  # instants two cameras must both see the board at for their link to count


# A pair's relative pose estimates from different instants should agree to the corners' noise (a fraction of a
# degree); unsynchronised videos of a moving board spread by tens of degrees.
MAX_PAIR_SPREAD_DEG = 5.0


# ----------------------------------------------------------------------------------------- initialisation
def usable(view: RigView, board: BoardSpec, min_corners: int) -> str | None:
    """None when ``view`` can be used, else why not."""
    if len(view.ids) < min_corners:
        return f"{len(view.ids)} corners (fewer than {min_corners})" if len(view.ids) else "no board found"
    points = board.object_points()[view.ids, :2]
    spread = np.linalg.svd(points - points.mean(0), compute_uv=False)
    if spread[1] < MIN_SPREAD_RATIO * spread[0]:
        return "corners along one line of the board"
    return None


def view_pose(view: RigView, board: BoardSpec, camera: Camera) -> tuple[np.ndarray, np.ndarray, float]:
    """The board's pose in ``view``'s camera, (R (3, 3), t (3,), RMS px of the fit)."""
    objects = board.object_points()[view.ids]
    if camera.model == "fisheye":
        return _fisheye_view_pose(objects, view.corners, camera)
    ok, rvec, tvec = cv2.solvePnP(objects, view.corners, camera.K, camera.dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return np.eye(3), np.zeros(3), math.inf
    rvec, tvec = cv2.solvePnPRefineLM(objects, view.corners, camera.K, camera.dist, rvec, tvec)
    reprojected = cv2.projectPoints(objects, rvec, tvec, camera.K, camera.dist)[0].reshape(-1, 2)
    rms = float(np.sqrt(np.mean(np.sum((reprojected - view.corners) ** 2, axis=1))))
    return cv2.Rodrigues(rvec)[0], tvec.ravel(), rms


# A fisheye view's first pose comes from its corners undistorted onto the plane z = 1, where a ray 75 degrees off
# the axis lands at 3.7 and its pixel noise is magnified 15x (1 / cos^2 of the angle, against the axis's), nearer 90
# degrees without bound: the corners within this angle start it, all of them refine it in pixels.
FISHEYE_START_DEG = 75.0
# A 180 degree lens sees corners at 90 degrees off its axis, and a pose from the starting intrinsics may put one a
# little past that (the rig's fisheye projection takes the ray's angle as it is, to 180 degrees)
FISHEYE_BEHIND_DEG = 20.0


def _fisheye_view_pose(objects: np.ndarray, corners: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray, float]:
    """`view_pose` through OpenCV's fisheye model: ``cv2.fisheye.undistortPoints`` to normalised coordinates, PnP
    (IPPE) on those within `FISHEYE_START_DEG` of the axis (all, where fewer than 4 are), then Levenberg-Marquardt
    on every corner's pixel error (``scipy.optimize.least_squares``, the rig's `project_fisheye`)."""
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    normalised = cv2.fisheye.undistortPoints(corners.reshape(-1, 1, 2), camera.K, camera.dist,
                                             criteria=criteria).reshape(-1, 2)
    finite = np.all(np.isfinite(normalised), axis=1)
    near = finite & (np.hypot(normalised[:, 0], normalised[:, 1]) < math.tan(math.radians(FISHEYE_START_DEG)))
    start = near if near.sum() >= 4 else finite
    if start.sum() < 4:
        return np.eye(3), np.zeros(3), math.inf
    try:
        ok, rvec, tvec = cv2.solvePnP(objects[start], normalised[start], np.eye(3), None, flags=cv2.SOLVEPNP_IPPE)
    except cv2.error:
        ok = False
    if not ok or not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
        return np.eye(3), np.zeros(3), math.inf
    intrinsics = np.tile(intrinsic_vector(camera), (len(objects), 1))

    def residuals(x: np.ndarray) -> np.ndarray:
        in_camera = objects @ rotations_from_vectors(x[:3])[0].T + x[3:]
        return (project_fisheye(in_camera, intrinsics) - corners).ravel()

    solution = least_squares(residuals, np.concatenate([rvec.ravel(), tvec.ravel()]), method="lm", xtol=1e-12,
                             ftol=1e-12)
    rms = float(np.sqrt(np.mean(solution.fun.reshape(-1, 2) ** 2) * 2))
    return rotations_from_vectors(solution.x[:3])[0], solution.x[3:].copy(), rms


def view_poses(views: list[RigView], boards: list[BoardSpec], cameras: list[Camera], min_corners: int
               ) -> tuple[dict[tuple[int, tuple[int, int]], tuple[np.ndarray, np.ndarray]], list[RigView], list[Dropped]]:
    """Each usable view's board pose {(camera, (instant, board)): (R, t)}, the usable views, and the others with
    why."""
    poses, kept, dropped = {}, [], []
    for view in views:
        reason = usable(view, boards[view.board], min_corners)
        if reason is None:
            R, t, rms = view_pose(view, boards[view.board], cameras[view.camera])
            # The corners seen lie ahead of the camera; a fisheye lens's up to `FISHEYE_BEHIND_DEG` past its side
            # (its board's origin may lie behind it)
            points = boards[view.board].object_points()[view.ids] @ R.T + t
            floor = -math.sin(math.radians(FISHEYE_BEHIND_DEG)) if cameras[view.camera].model == "fisheye" else 0.0
            ahead = points[:, 2] > floor * np.linalg.norm(points, axis=1)
            if rms > MAX_VIEW_POSE_PX or not ahead.all():
                dropped.append(Dropped(view.camera, view.instant, view.name, len(view.ids), "pose",
                                       f"no pose of the board fits its corners (RMS {rms:.1f} px > {MAX_VIEW_POSE_PX:g})",
                                       view.board))
                continue
            poses[(view.camera, view.key)] = (R, t)
            kept.append(view)
        elif len(view.ids):
            dropped.append(Dropped(view.camera, view.instant, view.name, len(view.ids), "detection", reason, view.board))
    return poses, kept, dropped


@dataclass
class PairEstimate:
    """Camera j's frame to camera i's, x_i = R x_j + t, from ``count`` shared instants, and how far the instants'
    own estimates spread about it (median rotation angle, degrees; median translation, metres)."""

    R: np.ndarray
    t: np.ndarray
    count: int
    spread_deg: float
    spread_m: float


def relative_poses(poses: dict[tuple[int, tuple[int, int]], tuple[np.ndarray, np.ndarray]], n_cameras: int
                   ) -> dict[tuple[int, int], PairEstimate]:
    """{(i, j): PairEstimate} for every pair i < j of cameras that both saw one board at an instant (`view_poses`'
    poses, keyed (camera, (instant, board)))."""
    by_instant: dict[tuple[int, int], list[int]] = {}
    for camera, instant in poses:
        by_instant.setdefault(instant, []).append(camera)
    candidates: dict[tuple[int, int], list[tuple[np.ndarray, np.ndarray]]] = {}
    for instant, seen in by_instant.items():
        for i in seen:
            for j in seen:
                if i < j:
                    R_i, t_i = poses[(i, instant)]
                    R_j, t_j = poses[(j, instant)]
                    candidates.setdefault((i, j), []).append(compose(R_i, t_i, *invert(R_j, t_j)))
    pairs = {}
    for key, estimates in candidates.items():
        rotations = np.stack([R for R, _ in estimates])
        translations = np.stack([t for _, t in estimates])
        scale = max(float(np.median(np.linalg.norm(translations, axis=1))), 1e-6)
        # Rotation angle between every two estimates (degrees) plus the translation difference as the angle it
        # subtends at the baseline's length.
        relative = np.einsum("aji,bjk->abik", rotations, rotations)
        angles = np.degrees(np.arccos(np.clip((np.trace(relative, axis1=2, axis2=3) - 1) / 2, -1, 1)))
        distances = angles + np.degrees(np.linalg.norm(translations[:, None] - translations[None], axis=2) / scale)
        medoid = int(np.argmin(np.median(distances, axis=1)))
        others = np.arange(len(estimates)) != medoid
        spread_deg = float(np.median(angles[medoid, others])) if others.any() else 0.0
        spread_m = float(np.median(np.linalg.norm(translations[others] - translations[medoid], axis=1))) if others.any() else 0.0
        pairs[key] = PairEstimate(rotations[medoid], translations[medoid], len(estimates), spread_deg, spread_m)
    return pairs


def chain_cameras(pairs: dict[tuple[int, int], PairEstimate], names: list[str]
                  ) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int]]]:
    """Each camera's pose in camera 0's frame, (C, 3, 3) and (C, 3), linked along the pairs sharing the most
    instants (Prim's maximum spanning tree from camera 0), and the tree's links (parent, child)."""
    n = len(names)
    rotations, translations = np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3))
    linked, links = {0}, []
    while len(linked) < n:
        best = None
        for (i, j), pair in pairs.items():
            if pair.count < MIN_SHARED_VIEWS or (i in linked) == (j in linked):
                continue
            if best is None or pair.count > best[1].count:
                best = ((i, j), pair)
        if best is None:
            alone = [c for c in range(n) if c not in linked]
            counts = {c: max([p.count for (i, j), p in pairs.items() if c in (i, j)] or [0]) for c in alone}
            c = alone[0]
            raise RigError(
                f"camera {names[c]} sees the board at the same instant as another camera in {counts[c]} view(s) "
                f"(at least {MIN_SHARED_VIEWS} needed to place it in the rig): hold the board where {names[c]} and "
                f"one of {', '.join(names[k] for k in sorted(linked))} both see it, at several places")
        (i, j), pair = best
        if i in linked:  # x_j = R^T (x_i - t): camera i's frame to camera j's
            R_ji, t_ji = invert(pair.R, pair.t)
            rotations[j], translations[j] = compose(R_ji, t_ji, rotations[i], translations[i])
            linked.add(j)
            links.append((i, j))
        else:
            rotations[i], translations[i] = compose(pair.R, pair.t, rotations[j], translations[j])
            linked.add(i)
            links.append((j, i))
    return rotations, translations, links


def check_synchronised(pairs: dict[tuple[int, int], PairEstimate], names: list[str]) -> None:
    """Refuse pairs whose per-instant relative poses disagree beyond `MAX_PAIR_SPREAD_DEG`: unsynchronised videos."""
    for (i, j), pair in sorted(pairs.items()):
        if pair.count >= MIN_SHARED_VIEWS and pair.spread_deg > MAX_PAIR_SPREAD_DEG:
            raise RigError(
                f"cameras {names[i]} and {names[j]} disagree on where they stand relative to each other from one "
                f"instant to the next (median {pair.spread_deg:.1f} degrees over {pair.count} shared instants; a still "
                f"rig gives < 1): the videos are not synchronised frame by frame: give --sync auto (lined up by the "
                f"board's motion), --sync-offsets (the frames to skip at each video's start so that they line up) or "
                f"record them together")
