"""Several cameras calibrated together from synchronised views of one or more ChArUco boards (a rig).

The steps (`calibrate_rig` runs them in order; the rig's data types in `rig_model`, steps 1-3 in `rig_init`,
steps 5-6 in `bundle`):

1. `view_poses`: every view (a camera's frame of one board at one instant) with at least ``min_corners`` corners
   not along one line gets the board's pose in that camera (``cv2.solvePnP`` IPPE, then Levenberg-Marquardt, under
   the camera's starting intrinsics; a fisheye camera's corners undistorted first, `rig_init._fisheye_view_pose`); a
   view whose corners that pose does not fit (RMS above `MAX_VIEW_POSE_PX`)
   is dropped;
2. `relative_poses`: for each pair of cameras, each instant both see one board at gives one estimate of where one
   camera is relative to the other; the estimate nearest all the others (the medoid) is kept, and the spread of
   the others about it is how far the pair disagrees with itself: beyond `MAX_PAIR_SPREAD_DEG` the videos are not
   synchronised (a moving board seen at two different moments gives a different relative pose each time);
3. `chain_cameras`: the cameras are linked from camera 0 along the pairs that share the most instants (a maximum
   spanning tree), so a camera that never shares a view with camera 0 is reached through the others; a camera
   that shares fewer than `MIN_SHARED_VIEWS` instants with all the others is refused, saying what to capture;
4. each (instant, board)'s pose in the rig's frame (camera 0's) from the view of it with the most corners;
5. `bundle_adjust`: ``scipy.optimize.least_squares`` (trust region, sparse Jacobian in closed form (`rig_jacobian`; finite differences with a fisheye camera), Huber loss
   of scale `HUBER_PX`) over every camera's free intrinsics (fx fy cx cy and its distortion terms), every camera's
   pose but camera 0's, and every (instant, board)'s pose, minimising the corners' reprojection error in every
   view (each corner weighed by its detector's covariance and its view's excess where the views carry covariances:
   `corner_weights`), with each camera's own calibration as a prior on its intrinsics (`PRIOR_NOTE`); where the cameras
   disagree beyond their own noise (`MAX_DISAGREEMENT`) the intrinsics are held instead. Corners farther than
   `CORNER_OUTLIER` x the robust sigma (and 2 px) from their reprojection, then views whose RMS exceeds
   `VIEW_OUTLIER` x the median view's (and 1 px), are dropped and it is solved again (at most `MAX_ROUNDS` times);
   each drop is said with its reason;
6. the parameters' standard deviations (`_global_covariance`): the Gauss-Newton covariance scaled by the
   residuals, or the instants' cluster-robust estimate where larger, the board poses eliminated (Schur complement).

Conventions: OpenCV's pixels (centre of the top-left pixel at (0, 0)) and distortion models: k1 k2 p1 p2 k3
[k4 k5 k6] (``cv2.projectPoints``), or a camera of the fisheye model (`Camera.model`) cv2.fisheye's k1..k4
(``cv2.fisheye.projectPoints``), one model per camera, so a rig may mix them; a camera's pose (R, t) maps the
rig's frame to the camera's: x_cam = R X + t, in metres (the
board's units). The boards' points are `BoardSpec.object_points` (z = 0 on the board).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.calibration.bundle import bundle_adjust, corner_weights, free_mask, parameter_deviations
from deepcharuco.calibration.intrinsics import MAX_RELATIVE_STD, MIN_FOLD_SHARE, fold_share
from deepcharuco.calibration.rig_init import chain_cameras, check_synchronised, relative_poses, view_poses
from deepcharuco.calibration.rig_model import (FISHEYE_TERMS, INTRINSICS, Dropped, RigError, RigResult, RigView,
                                               camera_from_vector, compose, intrinsic_vector, invert)
from deepcharuco.core.errors import OptionError
from deepcharuco.geometry.camera import Camera


# PRIOR_NOTE: each camera's own calibration (`calibration.calibrate`: its views selected, weighed and
# cross-validated) is a prior on its intrinsics in the joint solve, with its standard deviations, so that the rig's
# corners move an intrinsic only as far as they outweigh that camera's own evidence. The prior's residual
# (value - start) / deviation counts in deviations, the corners' in px, so it is scaled by the rig's corner noise,
# measured by a first solve with the intrinsics held. It was added after caliscope's four webcams, where the joint
# solve without it moved fx by 2-8 % from every camera's own calibration (and from caliscope's), at deviations of
# 1-3 %; those cameras are now held by `MAX_DISAGREEMENT`. On the drawn validation rig (seed 0) it changed little:
# worst rotation 0.039 -> 0.039 degrees, camera centre 1.41 -> 1.61 mm/m, fx 0.04 -> 0.06 %. The same corners enter
# both the prior and the rig, which counts them twice.
CORNER_OUTLIER = 5.0
VIEW_OUTLIER = 3.0
MIN_VIEW_OUTLIER_PX = 1.0
MAX_ROUNDS = 4


# When the cameras' views of one instant disagree by more than this x each camera's own corner noise (its own
# calibration's), the rig's model does not hold (cameras not synchronised to the frame, rolling shutters, a board
# that flexes) and a joint solve would bend the intrinsics to absorb it: they are held at each camera's own
# calibration. The validation drawn rig (seed 0) read 0.6-1.3 x (good light, dark, shake; OpenCV's and the deep
# detector's corners); caliscope's four webcams (6 fps, free-running) 7.8 x, where freeing the intrinsics moved fx
# 2-8 % from every camera's own calibration and from caliscope's (chosen after seeing that: caliscope does not
# measure this rule independently).
MAX_DISAGREEMENT = 2.5


# WEIGHT_NOTE: solves per round when the corners weigh by their covariances (`corner_weights`): the first with the
# excess measured by the round before (or none), the next with the excess its own residuals show.
WEIGHT_PASSES = 2
PINHOLE_TERMS = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")  # a pinhole camera's slots: its first 5 or 8


def calibrate_rig(views: list[RigView], board: BoardSpec | list[BoardSpec], cameras: list[Camera], names: list[str],
                  terms: list[str | None], *, min_corners: int = 6, priors: list[dict[str, float] | None] | None = None,
                  own_noise: list[float | None] | None = None, weigh_corners: bool = True) -> RigResult:
    """Calibrate the rig from ``views`` (module docstring), starting from each camera's intrinsics ``cameras``
    (a single-camera calibration, or a given file). ``terms[c]``: the distortion terms camera c solves
    ("k1 k2 p1 p2 k3", ...), or None to hold its intrinsics fixed. ``priors[c]``: {intrinsic name: standard
    deviation} of camera c's starting intrinsics (`PRIOR_NOTE`), or None: no prior. ``own_noise[c]``: camera
    c's corner noise in its own calibration (px per axis): a rig whose cameras disagree by more than
    `MAX_DISAGREEMENT` x that holds every camera's intrinsics. ``weigh_corners``: where every view carries its
    corners' covariances, each corner weighs by them and its view's excess (`corner_weights`).

    Raises:
        OptionError: fewer than two cameras.
        RigError: (a `CalibrationError`) views that cannot give a rig: a camera sharing too few instants with the
            others, pairs whose relative poses spread as unsynchronised videos do, a diverged solve; saying what to
            capture or pass instead.
    """
    n = len(cameras)
    if n < 2:
        raise OptionError("a rig has two cameras or more; calibrate one camera with deepcharuco.calibration.calibrate")
    boards = [board] if isinstance(board, BoardSpec) else list(board)
    poses, kept, dropped = view_poses(views, boards, cameras, min_corners)
    for c in range(n):
        if not any(v.camera == c for v in kept):
            raise RigError(f"camera {names[c]} has no usable view of the board ({min_corners}+ corners not along one "
                           f"line): check that it sees the board, lit and in focus")
    pairs = relative_poses(poses, n)
    check_synchronised(pairs, names)
    rotations, translations, _ = chain_cameras(pairs, names)
    board_poses = {}
    for key in sorted({v.key for v in kept}):
        seen = [v for v in kept if v.key == key]
        best = max(seen, key=lambda v: len(v.ids))
        R, t = poses[(best.camera, key)]
        board_poses[key] = compose(*invert(rotations[best.camera], translations[best.camera]), R, t)
    sizes = [camera.image_size for camera in cameras]
    n_dist = [8 if camera.dist.size >= 8 else 5 for camera in cameras]
    fisheye = np.array([camera.model == "fisheye" for camera in cameras])
    slots = [FISHEYE_TERMS if fish else PINHOLE_TERMS[:d] for fish, d in zip(fisheye, n_dist)]
    free = np.stack([free_mask(t, s) for t, s in zip(terms, slots)])
    intrinsics = np.stack([intrinsic_vector(camera) for camera in cameras])
    start = intrinsics.copy()
    prior = np.full(intrinsics.shape, np.inf)
    for c, deviations in enumerate(priors or []):
        for p, name in enumerate(INTRINSICS):
            if deviations and name in deviations and deviations[name] > 0:
                prior[c, p] = deviations[name]
    notes: list[str] = []
    disagreement = math.nan
    weighing = weigh_corners and all(v.covariances is not None for v in kept)
    last: dict[tuple[int, tuple[int, int]], dict[int, np.ndarray]] = {}  # each view's last residual per corner ID

    def weights_for(views: list[RigView]) -> list[np.ndarray] | None:
        if not weighing:
            return None
        known = [last.get((v.camera, v.key)) for v in views]
        if any(k is None for k in known):
            return corner_weights(views)
        return corner_weights(views, [np.array([k[i] for i in v.ids.tolist()]) for v, k in zip(views, known)])

    def remember(views: list[RigView], residuals: list[np.ndarray]) -> None:
        for v, r in zip(views, residuals):
            last[(v.camera, v.key)] = dict(zip(v.ids.tolist(), r))

    own = [v for v in (own_noise or []) if v is not None and v > 0]
    if (np.isfinite(prior).any() or own) and free.any():
        # The rig's corner noise, the intrinsics held: the unit the prior's deviations are scaled into, and what the
        # cameras' own noise is compared with.
        _, rotations, translations, held, residuals, _, _ = bundle_adjust(
            kept, boards, intrinsics, np.zeros_like(free), rotations, translations, board_poses,
            weights=weights_for(kept), fisheye=fisheye)
        remember(kept, residuals)
        board_poses.update({key: (cv2.Rodrigues(r)[0], t) for key, (r, t) in held.items()})
        stacked = np.concatenate(residuals)
        noise = math.sqrt(float(np.median(np.sum(stacked ** 2, axis=1))) / (2 * math.log(2)))  # robust, per axis
        prior = prior / max(noise, 1e-6)
        disagreement = noise / float(np.median(own)) if own else math.nan
        if own and disagreement > MAX_DISAGREEMENT:
            free[:] = False
            notes.append(f"the cameras' views of one instant disagree by {noise:.2f} px, {noise / np.median(own):.1f} x "
                         f"the cameras' own corner noise ({np.median(own):.2f} px): the cameras are not synchronised to "
                         f"the frame (or have rolling shutters), so each camera's intrinsics are held at its own "
                         f"calibration and the deviations of the poses leave out theirs; record with synchronised "
                         f"cameras, or give --sync-offsets")
    active = kept
    masks = [np.ones(len(v.ids), bool) for v in active]
    outliers: set[tuple[int, tuple[int, int]]] = set()
    rounds = 0
    while True:
        rounds += 1
        used = [v.subset(m) for v, m in zip(active, masks) if (v.camera, v.key) not in outliers]
        poses_used = {key: board_poses[key] for key in sorted({v.key for v in used})}
        # Weighed by the corners' covariances, each round solves twice: the second time with the views' excess
        # measured by the first (WEIGHT_NOTE).
        for _ in range(WEIGHT_PASSES if weighing else 1):
            solved, rotations, translations, board_poses_new, residuals, covariance, problem = bundle_adjust(
                used, boards, intrinsics, free, rotations, translations, poses_used, prior, start, weights_for(used),
                fisheye)
            remember(used, residuals)
            board_poses.update({i: (cv2.Rodrigues(r)[0], t) for i, (r, t) in board_poses_new.items()})
            poses_used = {key: board_poses[key] for key in poses_used}
            intrinsics = solved
        if rounds >= MAX_ROUNDS or not _reject(active, masks, outliers, used, residuals, dropped, min_corners):
            break
    result_cameras = [camera_from_vector(intrinsics[c], sizes[c], n_dist[c], cameras[c].model) for c in range(n)]
    for c, camera in enumerate(result_cameras):
        if not free[c].any():
            continue  # held at its own calibration, which checked it, or at a given file
        fold = fold_share(camera)
        if fold is not None and fold < MIN_FOLD_SHARE:
            if terms[c] is not None and "k3" in terms[c].split():
                fewer = list(terms)
                fewer[c] = " ".join(t for t in terms[c].split() if t != "k3")
                result = calibrate_rig(views, boards, cameras, names, fewer, min_corners=min_corners, priors=priors,
                                       own_noise=own_noise, weigh_corners=weigh_corners)
                result.notes.insert(0, f"{names[c]}: with k3 free its distortion folds back {100 * fold:.0f} % of the "
                                       f"way to the image's corner: solved again with k3 fixed at 0")
                return result
            raise RigError(f"{names[c]}'s distortion folds back {100 * fold:.0f} % of the way to the image's corner, "
                           f"so the image beyond cannot be undistorted: capture the board near that camera's edges and "
                           f"corners too")
        if fold is not None:
            notes.append(f"{names[c]}: the distortion folds back {100 * fold:.0f} % of the way to the image's corner "
                         f"(the corners' tips only)")
    std = parameter_deviations(problem, covariance, names)
    for c, deviations in enumerate(priors or []):
        if deviations and not free[c].any():  # held at its own calibration: that calibration's deviations
            std[c] = {**{k: v for k, v in deviations.items() if k in INTRINSICS}, **std[c]}
    for c in range(n):
        for name, value in (("fx", intrinsics[c, 0]), ("fy", intrinsics[c, 1])):
            if std[c].get(name, 0.0) > MAX_RELATIVE_STD * value:
                raise RigError(f"{names[c]}: {name} = {value:.1f} +- {std[c][name]:.1f} px is too uncertain (> "
                               f"{100 * MAX_RELATIVE_STD:.0f} %): capture the board tilted 20-40 degrees in several "
                               f"directions and near that camera's edges and corners")
    shared: dict[tuple[int, int], int] = {}
    seen_at: dict[tuple[int, int], set[int]] = {}
    for v in used:
        seen_at.setdefault(v.key, set()).add(v.camera)
    for seen in seen_at.values():
        for i in seen:
            for j in seen:
                if i < j:
                    shared[(i, j)] = shared.get((i, j), 0) + 1
    terms_used = [terms[c] if terms[c] is not None and free[c].any() else "" for c in range(n)]
    final_poses = {i: (cv2.Rodrigues(board_poses[i][0])[0].ravel(), np.asarray(board_poses[i][1], np.float64))
                   for i in sorted(seen_at)}
    return RigResult(result_cameras, list(names), rotations, translations, final_poses, used, residuals, std,
                     shared, dropped, notes, terms_used, rounds, disagreement, weighing)


def _reject(active: list[RigView], masks: list[np.ndarray], outliers: set, used: list[RigView],
            residuals: list[np.ndarray], dropped: list[Dropped], min_corners: int) -> bool:
    """Drop outlier corners, then outlier views (module docstring); True when anything changed."""
    norms = [np.linalg.norm(r, axis=1) for r in residuals]
    everything = np.concatenate(norms)
    sigma = 1.4826 * float(np.median(everything)) / math.sqrt(2 * math.log(2))  # a 2-D residual's norm: Rayleigh
    corner_limit = max(CORNER_OUTLIER * sigma, 2.0)
    changed = False
    position = {(v.camera, v.key): k for k, v in enumerate(active)}
    view_rms = np.array([math.sqrt(float(np.mean(n ** 2))) for n in norms])
    view_limit = max(VIEW_OUTLIER * float(np.median(view_rms)), MIN_VIEW_OUTLIER_PX)
    for v, n, rms in zip(used, norms, view_rms):
        k = position[(v.camera, v.key)]
        if rms > view_limit:
            outliers.add((v.camera, v.key))
            dropped.append(Dropped(v.camera, v.instant, v.name, len(v.ids), "outlier",
                                   f"RMS {rms:.2f} px > {view_limit:.2f} px ({VIEW_OUTLIER:g} x the median view)", v.board))
            changed = True
            continue
        bad = n > corner_limit
        if bad.any() and masks[k].sum() - bad.sum() >= min_corners:
            kept_positions = np.flatnonzero(masks[k])
            masks[k][kept_positions[bad]] = False
            changed = True
    return changed
