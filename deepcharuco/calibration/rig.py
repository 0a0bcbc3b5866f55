"""Several cameras calibrated together from synchronised views of one or more ChArUco boards (a rig).

The steps (`calibrate_rig` runs them in order):

1. `view_poses`: every view (a camera's frame of one board at one instant) with at least ``min_corners`` corners
   not along one line gets the board's pose in that camera (``cv2.solvePnP`` IPPE, then Levenberg-Marquardt, under
   the camera's starting intrinsics); a view whose corners that pose does not fit (RMS above `MAX_VIEW_POSE_PX`)
   is dropped;
2. `relative_poses`: for each pair of cameras, each instant both see one board at gives one estimate of where one
   camera is relative to the other; the estimate nearest all the others (the medoid) is kept, and the spread of
   the others about it is how far the pair disagrees with itself: beyond `MAX_PAIR_SPREAD_DEG` the videos are not
   synchronised (a moving board seen at two different moments gives a different relative pose each time);
3. `chain_cameras`: the cameras are linked from camera 0 along the pairs that share the most instants (a maximum
   spanning tree), so a camera that never shares a view with camera 0 is reached through the others; a camera
   that shares fewer than `MIN_SHARED_VIEWS` instants with all the others is refused, saying what to capture;
4. each (instant, board)'s pose in the rig's frame (camera 0's) from the view of it with the most corners;
5. `bundle_adjust`: ``scipy.optimize.least_squares`` (trust region, sparse finite-difference Jacobian, Huber loss
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

Conventions: OpenCV's pixels (centre of the top-left pixel at (0, 0)) and distortion model (k1 k2 p1 p2 k3
[k4 k5 k6]); a camera's pose (R, t) maps the rig's frame to the camera's: x_cam = R X + t, in metres (the
board's units). The boards' points are `BoardSpec.object_points` (z = 0 on the board).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix

from deepcharuco.boards.board import BoardSpec
from deepcharuco.calibration.calibration import (
    MAX_RELATIVE_STD, MIN_FOLD_SHARE, CalibrationError, checked_covariances, fold_share, view_excess,
)
from deepcharuco.core.errors import OptionError
from deepcharuco.geometry.camera import Camera
from deepcharuco.geometry.pose import MIN_SPREAD_RATIO

# Intrinsic parameters of a camera in the bundle adjustment, in this order (OpenCV's pinhole and rational models).
INTRINSICS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
MAX_VIEW_POSE_PX = 4.0  # a view whose own PnP pose leaves an RMS above this is a misdetection or a wrong camera model
MIN_SHARED_VIEWS = 3  # instants two cameras must both see the board at for their link to count
# A pair's relative pose estimates from different instants should agree to the corners' noise (a fraction of a
# degree); unsynchronised videos of a moving board spread by tens of degrees.
MAX_PAIR_SPREAD_DEG = 5.0
HUBER_PX = 1.0  # residuals beyond this count linearly in the bundle adjustment
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
# least_squares' sparse trust-region steps come from LSMR; at its default tolerances (1e-6) a 3-camera problem took
# 200+ steps and stopped short (fx 2 % off its start moved back only half way); at 1e-12 it converges in ~50.
MAX_STEPS = 300
# WEIGHT_NOTE: solves per round when the corners weigh by their covariances (`corner_weights`): the first with the
# excess measured by the round before (or none), the next with the excess its own residuals show.
WEIGHT_PASSES = 2
MIN_VARIANCE_PX2 = 1e-8  # added to every corner's covariance: a degenerate one must not weigh infinitely


class RigError(CalibrationError):
    """Views that cannot give a rig; the message says what to capture or give instead."""


@dataclass
class RigView:
    """One camera's detection of one board at one instant: ``ids`` (N,) int64, ``corners`` (N, 2) float64 pixels,
    ``name`` the frame's name in its source, ``board`` the board's index (several boards: `calibrate_rig`),
    ``covariances`` (N, 2, 2) px^2 each corner's covariance from its detector (`Detection.covariances`; None: not
    given, and the corners weigh alike)."""

    camera: int
    instant: int
    ids: np.ndarray
    corners: np.ndarray
    name: str = ""
    board: int = 0
    covariances: np.ndarray | None = None

    @property
    def key(self) -> tuple[int, int]:
        """(instant, board): what one board pose is solved for."""
        return self.instant, self.board

    def __post_init__(self) -> None:
        self.ids = np.asarray(self.ids, np.int64).reshape(-1)
        self.corners = np.asarray(self.corners, np.float64).reshape(-1, 2)
        self.covariances = checked_covariances(self.covariances)

    def subset(self, keep: np.ndarray) -> "RigView":
        """The view with only the corners ``keep`` (a boolean mask or indices) selects."""
        covariances = None if self.covariances is None else self.covariances[keep]
        return RigView(self.camera, self.instant, self.ids[keep], self.corners[keep], self.name, self.board, covariances)


@dataclass
class Dropped:
    """A view left out and why: stage "detection" | "pose" | "outlier"."""

    camera: int
    instant: int
    name: str
    corners: int
    stage: str
    reason: str
    board: int = 0

    def to_dict(self) -> dict:
        return {"camera": self.camera, "instant": self.instant, "board": self.board, "name": self.name,
                "corners": self.corners, "stage": self.stage, "reason": self.reason}


@dataclass
class RigResult:
    """A solved rig.

    Attributes:
        cameras: each camera's intrinsics; names: their names (video stems).
        rotations: (C, 3, 3) and translations: (C, 3) metres: x_cam = R X + t, X in the rig's frame (camera 0's).
        board_poses: {(instant, board): (rvec (3,), tvec (3,))} each board -> the rig's frame at each instant used.
        views: the views used (their corners after outlier rejection); residuals: per view (N_v, 2) detected
            minus reprojected pixels.
        std: per camera {name: standard deviation}: the free intrinsics (px, unitless distortion) and the pose's
            "rotation_deg" (the rotation vector's largest axis deviation, degrees) and "tx" "ty" "tz" (metres).
        shared: {(i, j): instants both cameras i < j saw one board at (counted once per board), among the views used}.
        dropped: the views left out and why; notes: what the user should know; terms: per camera the distortion
            terms solved ("" when its intrinsics were held fixed).
    """

    cameras: list[Camera]
    names: list[str]
    rotations: np.ndarray
    translations: np.ndarray
    board_poses: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]]
    views: list[RigView]
    residuals: list[np.ndarray]
    std: list[dict[str, float]]
    shared: dict[tuple[int, int], int]
    dropped: list[Dropped]
    notes: list[str] = field(default_factory=list)
    terms: list[str] = field(default_factory=list)
    rounds: int = 1
    # the cameras' disagreement: the rig's corner noise (intrinsics held) over the cameras' own (`MAX_DISAGREEMENT`)
    disagreement: float = math.nan
    corners_weighed: bool = False  # each corner weighed by its detector's covariance and its view's excess

    def camera_rms(self, camera: int) -> float:
        """RMS reprojection error (px, per corner) of ``camera``'s views used."""
        r = [res for v, res in zip(self.views, self.residuals) if v.camera == camera]
        if not r:
            return math.nan
        stacked = np.concatenate(r)
        return float(np.sqrt(np.mean(np.sum(stacked ** 2, axis=1))))

    @property
    def rms(self) -> float:
        stacked = np.concatenate(self.residuals)
        return float(np.sqrt(np.mean(np.sum(stacked ** 2, axis=1))))

    def camera_views(self, camera: int) -> int:
        return sum(v.camera == camera for v in self.views)

    def centre(self, camera: int) -> np.ndarray:
        """(3,) the camera's centre in the rig's frame (metres)."""
        return -self.rotations[camera].T @ self.translations[camera]

    def reframed(self, rotation: np.ndarray, translation: np.ndarray) -> "RigResult":
        """The same rig in another frame: X_rig = rotation @ X_new + translation (e.g. the board's at an instant)."""
        rotations = self.rotations @ rotation
        translations = np.einsum("cij,j->ci", self.rotations, translation) + self.translations
        inverse_r, inverse_t = rotation.T, -rotation.T @ translation
        poses = {}
        for key, (rvec, tvec) in self.board_poses.items():
            R = cv2.Rodrigues(rvec)[0]
            poses[key] = (cv2.Rodrigues(inverse_r @ R)[0].ravel(), inverse_r @ tvec + inverse_t)
        return RigResult(self.cameras, self.names, rotations, translations, poses, self.views, self.residuals,
                         self.std, self.shared, self.dropped, list(self.notes), list(self.terms), self.rounds,
                         self.disagreement, self.corners_weighed)

    def summary(self) -> dict:
        """JSON-ready numbers: per camera its intrinsics, pose, RMS, views and deviations; pairs; drops."""
        cameras = []
        for c, camera in enumerate(self.cameras):
            K = camera.K
            cameras.append({"name": self.names[c], "image_size": list(camera.image_size), "fx": K[0, 0], "fy": K[1, 1],
                            "cx": K[0, 2], "cy": K[1, 2], "dist": camera.dist.tolist(),
                            "rotation_matrix": self.rotations[c].tolist(), "translation_m": self.translations[c].tolist(),
                            "centre_m": self.centre(c).tolist(), "rms_px": self.camera_rms(c),
                            "views": self.camera_views(c), "std": self.std[c],
                            "terms": self.terms[c] if c < len(self.terms) else ""})
        return {"cameras": cameras, "rms_px": self.rms, "instants": len({i for i, _ in self.board_poses}),
                "board_poses": len(self.board_poses),
                "shared_views": {f"{self.names[i]}-{self.names[j]}": n for (i, j), n in sorted(self.shared.items())},
                "dropped": [d.to_dict() for d in self.dropped], "notes": self.notes, "rounds": self.rounds,
                "disagreement": self.disagreement, "corners_weighed": self.corners_weighed}


# ----------------------------------------------------------------------------------------- geometry
def rotations_from_vectors(rvecs: np.ndarray) -> np.ndarray:
    """(K, 3, 3) rotation matrices of the (K, 3) rotation vectors (Rodrigues' formula, exact near 0)."""
    rvecs = np.asarray(rvecs, np.float64).reshape(-1, 3)
    theta = np.linalg.norm(rvecs, axis=1)
    small = theta < 1e-12
    axis = rvecs / np.where(small, 1.0, theta)[:, None]
    x, y, z = axis.T
    zero = np.zeros_like(x)
    cross = np.stack([np.stack([zero, -z, y], 1), np.stack([z, zero, -x], 1), np.stack([-y, x, zero], 1)], 1)
    sin, cos = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    outer = axis[:, :, None] * axis[:, None, :]
    rotation = cos * np.eye(3) + sin * cross + (1 - cos) * outer
    rotation[small] = np.eye(3)
    return rotation


def project(points_cam: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """(M, 2) pixels of the (M, 3) camera-frame points, each through its own (M, 12) intrinsics (`INTRINSICS`
    order): OpenCV's pinhole model, ``cv2.projectPoints``' formula."""
    fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6 = intrinsics.T
    z = points_cam[:, 2]
    x, y = points_cam[:, 0] / z, points_cam[:, 1] / z
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.column_stack([fx * xd + cx, fy * yd + cy])


def intrinsic_vector(camera: Camera) -> np.ndarray:
    """(12,) the camera's parameters in `INTRINSICS` order (absent distortion terms are 0)."""
    K = camera.K
    dist = np.pad(camera.dist, (0, max(0, 8 - camera.dist.size)))[:8]
    return np.concatenate([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], dist])


def camera_from_vector(vector: np.ndarray, image_size: tuple[int, int], terms: int) -> Camera:
    """The `Camera` of a (12,) `INTRINSICS` vector with ``terms`` distortion coefficients (5 or 8)."""
    fx, fy, cx, cy = vector[:4]
    return Camera(K=np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), dist=vector[4:4 + terms].copy(),
                  image_size=image_size)


def compose(R_a: np.ndarray, t_a: np.ndarray, R_b: np.ndarray, t_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The transform x -> a(b(x)) of two (R, t) transforms x -> R x + t."""
    return R_a @ R_b, R_a @ t_b + t_a


def invert(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return R.T, -R.T @ t


def rotation_angle_deg(R: np.ndarray) -> float:
    """The angle (degrees) of the rotation matrix ``R``."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


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
    ok, rvec, tvec = cv2.solvePnP(objects, view.corners, camera.K, camera.dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return np.eye(3), np.zeros(3), math.inf
    rvec, tvec = cv2.solvePnPRefineLM(objects, view.corners, camera.K, camera.dist, rvec, tvec)
    reprojected = cv2.projectPoints(objects, rvec, tvec, camera.K, camera.dist)[0].reshape(-1, 2)
    rms = float(np.sqrt(np.mean(np.sum((reprojected - view.corners) ** 2, axis=1))))
    return cv2.Rodrigues(rvec)[0], tvec.ravel(), rms


def view_poses(views: list[RigView], boards: list[BoardSpec], cameras: list[Camera], min_corners: int
               ) -> tuple[dict[tuple[int, tuple[int, int]], tuple[np.ndarray, np.ndarray]], list[RigView], list[Dropped]]:
    """Each usable view's board pose {(camera, (instant, board)): (R, t)}, the usable views, and the others with
    why."""
    poses, kept, dropped = {}, [], []
    for view in views:
        reason = usable(view, boards[view.board], min_corners)
        if reason is None:
            R, t, rms = view_pose(view, boards[view.board], cameras[view.camera])
            if rms > MAX_VIEW_POSE_PX or t[2] <= 0:
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
                f"rig gives < 1): the videos are not synchronised frame by frame: give --sync-offsets (the frames to "
                f"skip at each video's start so that they line up) or record them together")


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
        pixels = project(in_camera, intrinsics[self.camera]) - self.observed
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
                  prior_start: np.ndarray | None = None, weights: list[np.ndarray] | None = None):
    """One robust solve from the given start (board poses {(instant, board): (R (3, 3), t)}); ``prior`` (C, 12): the
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
        roots=None if weights is None else np.swapaxes(np.linalg.cholesky(np.concatenate(weights)), -1, -2))
    x0 = np.concatenate([intrinsics[free],
                         np.concatenate([_vectors(rotations[c], translations[c]) for c in range(1, len(intrinsics))])
                         if len(intrinsics) > 1 else np.zeros(0),
                         np.concatenate([_vectors(*board_poses[i]) for i in instants])])
    solution = least_squares(problem.residuals, x0, jac_sparsity=problem.sparsity(), method="trf", loss="huber",
                             f_scale=HUBER_PX, x_scale="jac", xtol=1e-10, ftol=1e-10, gtol=1e-10, max_nfev=MAX_STEPS,
                             tr_options={"atol": 1e-12, "btol": 1e-12})
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


def _global_covariance(problem: _Problem, solution, flat: np.ndarray) -> np.ndarray:
    """Covariance of the intrinsics and camera poses, each instant's board pose eliminated (Schur complement S of
    the Gauss-Newton matrix J^T J; J as the Huber loss weighs it, so rows beyond `HUBER_PX` count for ~nothing).
    Two estimates, and per
    parameter the larger variance:

    - the model's, S^-1 sigma^2 with sigma^2 = sum r^2 / (2N - parameters): right when every corner's error is
      independent (exact projections plus noise: errors / deviations spread 1.0-1.2 in `tests/test_rig.py`);
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


def _deviations(problem: _Problem, covariance: np.ndarray, names: list[str]) -> list[dict[str, float]]:
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
def free_mask(terms: str | None, n_dist: int) -> np.ndarray:
    """(12,) which `INTRINSICS` are solved: fx fy cx cy and the named distortion ``terms`` (e.g. "k1 k2 k3");
    None: nothing (intrinsics held as given)."""
    if terms is None:
        return np.zeros(12, bool)
    names = set(terms.split()) | {"fx", "fy", "cx", "cy"}
    return np.array([name in names and (i < 4 or i - 4 < n_dist) for i, name in enumerate(INTRINSICS)])


def calibrate_rig(views: list[RigView], board: BoardSpec | list[BoardSpec], cameras: list[Camera], names: list[str],
                  terms: list[str | None], *, min_corners: int = 6, priors: list[dict[str, float] | None] | None = None,
                  own_noise: list[float | None] | None = None, weigh_corners: bool = True) -> RigResult:
    """Calibrate the rig from ``views`` (module docstring), starting from each camera's intrinsics ``cameras``
    (a single-camera calibration, or a given file). ``terms[c]``: the distortion terms camera c solves
    ("k1 k2 p1 p2 k3", ...), or None to hold its intrinsics fixed. ``priors[c]``: {intrinsic name: standard
    deviation} of camera c's starting intrinsics (`PRIOR_NOTE`), or None: no prior. ``own_noise[c]``: camera
    c's corner noise in its own calibration (px per axis): a rig whose cameras disagree by more than
    `MAX_DISAGREEMENT` x that holds every camera's intrinsics. ``weigh_corners``: where every view carries its
    corners' covariances, each corner weighs by them and its view's excess (`corner_weights`)."""
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
    free = np.stack([free_mask(t, d) for t, d in zip(terms, n_dist)])
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
            weights=weights_for(kept))
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
                used, boards, intrinsics, free, rotations, translations, poses_used, prior, start, weights_for(used))
            remember(used, residuals)
            board_poses.update({i: (cv2.Rodrigues(r)[0], t) for i, (r, t) in board_poses_new.items()})
            poses_used = {key: board_poses[key] for key in poses_used}
            intrinsics = solved
        if rounds >= MAX_ROUNDS or not _reject(active, masks, outliers, used, residuals, dropped, min_corners):
            break
    result_cameras = [camera_from_vector(intrinsics[c], sizes[c], n_dist[c]) for c in range(n)]
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
    std = _deviations(problem, covariance, names)
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
