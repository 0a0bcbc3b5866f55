"""Drawn views of a board waved through a rig of fisheye cameras (~180 degree lenses) with exact truth.

No renderer and no intermediate pinhole image (a pinhole view cannot hold 180 degrees): every supersampled pixel
of the fisheye image is traced back to its ray through OpenCV's fisheye (equidistant) model, inverted by Newton's
method to 1e-13 rad (`pixel_rays`), the ray met with the board's plane, and the board's area-exact texture read
there (`render_fisheye_view`); the supersamples are box-filtered to pixels. A corner therefore lies where
``cv2.fisheye.projectPoints`` with the camera's (K, k1..k4) and pose puts it. Rays beyond 90 degrees off the axis
(outside the image circle) are black, as a circular fisheye's frame is.

The rig (`drawn_fisheye_rig`): ``cameras`` cameras 0.2-0.35 m apart on a bar, the first at the origin looking down
+z, the others turned 35-55 degrees to alternate sides about the vertical (wide lenses look different ways and
still share most of the scene); each lens's image circle, 180 degrees across, just fits the image's height
(f = the circle's radius / theta_d(90 degrees)), k1..k4 as a real equidistant lens's (k1 -0.03..+0.05, k2..k4
smaller). The board (`FISHEYE_BOARD`) is waved 0.45-1.1 m from the bar, anywhere up to 80 degrees to either side
and 50 up or down, facing the bar and tilted up to 40 degrees: in the middle of some images and near the edge of
the image circle in others. Conditions: `rig_views.degrade`'s ``good`` and ``dark``. Every random choice comes from
``seed``.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from datagen.lens import pixel_grid
from deepcharuco.boards.board import BoardSpec
from deepcharuco.geometry.camera import Camera
from evaluate.calibration.rig_views import DrawnRig, degrade, look_at

# A 7 x 5 board of 80 mm squares (A2): fisheye images are small where the board is far off the axis, so the
# squares are larger than the pinhole rigs' board's.
FISHEYE_BOARD = BoardSpec(squares_x=7, squares_y=5, square_length=0.08, marker_length=0.06, dictionary="DICT_6X6_250")
BACKGROUND = 90  # grey level of the room behind the board
NEWTON_STEPS = 12


def theta_d(theta: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """The fisheye model's distorted angle of the ray angles ``theta`` (radians): theta (1 + k1 theta^2 + ...)."""
    k1, k2, k3, k4 = dist
    t2 = theta * theta
    return theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))


def pixel_rays(camera: Camera, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 3) float32 unit rays of the (..., 2) pixels of the fisheye ``camera`` and (...,) bool: inside the image
    circle (the ray's angle at most 90 degrees; theta_d increases up to there for the lenses drawn here)."""
    (fx, _, cx), (_, fy, cy), _ = camera.K
    xd, yd = (pixels[..., 0] - cx) / fx, (pixels[..., 1] - cy) / fy
    distorted = np.hypot(xd, yd)
    inside = distorted <= float(theta_d(np.array(math.pi / 2), camera.dist))
    theta = np.where(inside, distorted, 0.0)
    k1, k2, k3, k4 = camera.dist
    for _ in range(NEWTON_STEPS):
        t2 = theta * theta
        slope = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
        theta = theta - (theta_d(theta, camera.dist) - np.where(inside, distorted, 0.0)) / slope
    scale = np.where(distorted > 1e-12, np.sin(theta) / np.maximum(distorted, 1e-12), 1.0)
    rays = np.stack([xd * scale, yd * scale, np.cos(theta)], axis=-1).astype(np.float32)
    return rays, inside


def render_fisheye_view(board: BoardSpec, camera: Camera, rvec: np.ndarray, tvec: np.ndarray, *,
                        supersample: int = 2, rays: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """(H, W) uint8: the printed board (half a square of white paper round the grid) at pose (rvec, tvec) through
    the fisheye ``camera`` (module docstring). ``rays``: `supersampled_rays` of this ``supersample``, when drawing
    many views through one camera."""
    width, height = camera.image_size
    if rays is None:
        rays = supersampled_rays(camera, supersample)
    directions, inside = rays
    R = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3))[0]
    t = np.asarray(tvec, np.float64).reshape(3)
    margin = 0.5 * board.square_length
    corners = np.array([[0, 0, 0], [board.size_m[0], 0, 0], [0, board.size_m[1], 0], [*board.size_m, 0]])
    nearest = max(float(np.linalg.norm(corners @ R.T + t, axis=1).min()), 0.05)
    px_per_m = float(np.clip(2 ** round(math.log2(1.5 * supersample * camera.K[0, 0] / nearest)), 256, 4096))
    texture = board.render_texture(px_per_m, margin)
    printed = texture.image if float(R[:, 2] @ t) > 0 else np.full_like(texture.image, 170)  # its back: plain
    # A ray d meets the board's plane at the board point (X, Y) with d ~ [r1 r2 t] (X, Y, 1): one 3 x 3 map from
    # rays to homogeneous texture pixels; a positive last coordinate means the plane lies ahead along the ray.
    to_texture = np.linalg.inv(texture.texture_to_board_matrix()) @ np.linalg.inv(np.column_stack([R[:, 0], R[:, 1], t]))
    uvw = directions @ to_texture.T.astype(np.float32)
    ahead = (uvw[..., 2] > 1e-9) & inside
    w = np.where(ahead, uvw[..., 2], 1.0)
    map_x = np.where(ahead, uvw[..., 0] / w, -1e4).astype(np.float32)
    map_y = np.where(ahead, uvw[..., 1] / w, -1e4).astype(np.float32)
    fine = cv2.remap(printed, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=BACKGROUND)
    fine[~inside] = 0
    return cv2.resize(fine, (width, height), interpolation=cv2.INTER_AREA)


def supersampled_rays(camera: Camera, supersample: int) -> tuple[np.ndarray, np.ndarray]:
    """`pixel_rays` of the centres of an s x s subsampling of each pixel (`datagen.lens.pixel_grid`)."""
    return pixel_rays(camera, pixel_grid(*camera.image_size, supersample))


def visible_corners(board: BoardSpec, camera: Camera, R: np.ndarray, t: np.ndarray, border: float = 2.0) -> np.ndarray:
    """(K,) the IDs of the board's corners a view shows: in front of the lens within 90 degrees of its axis, the
    board's printed face toward it, and at least ``border`` px inside the image."""
    points = board.object_points() @ R.T + t
    if float(R[:, 2] @ t) <= 0:  # the board's z (into the board) points toward the camera: its back is seen
        return np.zeros(0, np.int64)
    pixels = camera.project(board.object_points(), cv2.Rodrigues(R)[0], t)
    width, height = camera.image_size
    ahead = points[:, 2] > 1e-6
    inside = ((pixels[:, 0] >= border - 0.5) & (pixels[:, 0] <= width - 0.5 - border)
              & (pixels[:, 1] >= border - 0.5) & (pixels[:, 1] <= height - 0.5 - border))
    return np.flatnonzero(ahead & inside)


def fisheye_cameras(rng: np.random.Generator, count: int, size: tuple[int, int]
                    ) -> tuple[list[Camera], np.ndarray, np.ndarray]:
    """``count`` fisheye cameras (intrinsics, rotations (C, 3, 3), translations (C, 3); module docstring)."""
    width, height = size
    cameras, rotations, translations = [], [], []
    x, side = 0.0, 1
    for c in range(count):
        dist = np.array([rng.uniform(-0.03, 0.05), rng.uniform(-0.01, 0.01), rng.uniform(-0.003, 0.003),
                         rng.uniform(-0.001, 0.001)])
        radius = height / 2 - rng.uniform(2, 8)  # the 90 degree circle just inside the frame's height
        f = radius / float(theta_d(np.array(math.pi / 2), dist))
        K = np.array([[f, 0, (width - 1) / 2 + rng.uniform(-6, 6)], [0, f * rng.uniform(0.998, 1.002),
                                                                      (height - 1) / 2 + rng.uniform(-5, 5)], [0, 0, 1.0]])
        cameras.append(Camera(K, dist, size, model="fisheye"))
        if c == 0:
            rotations.append(np.eye(3))
            translations.append(np.zeros(3))
            continue
        x += side * rng.uniform(0.2, 0.35) * c
        yaw = side * math.radians(rng.uniform(35, 55))
        eye = np.array([x, rng.uniform(-0.03, 0.03), rng.uniform(-0.05, 0.05)])
        R, t = look_at(eye, eye + np.array([math.sin(yaw), rng.uniform(-0.1, 0.1), math.cos(yaw)]))
        rotations.append(R)
        translations.append(t)
        side = -side
    return cameras, np.stack(rotations), np.stack(translations)


def fisheye_board_poses(rng: np.random.Generator, board: BoardSpec, centre: np.ndarray, count: int
                        ) -> tuple[np.ndarray, np.ndarray]:
    """``count`` board poses (board -> camera 0's frame) about the rig's ``centre`` (module docstring)."""
    middle = np.array([board.size_m[0] / 2, board.size_m[1] / 2, 0.0])
    rotations, translations = [], []
    for _ in range(count):
        azimuth, elevation = math.radians(rng.uniform(-80, 80)), math.radians(rng.uniform(-50, 50))
        direction = np.array([math.sin(azimuth) * math.cos(elevation), math.sin(elevation),
                              math.cos(azimuth) * math.cos(elevation)])
        position = centre + rng.uniform(0.45, 1.1) * direction
        R_face, _ = look_at(centre, position)  # its z along the line of sight: the printed face toward the bar
        tilt = cv2.Rodrigues(np.radians([rng.uniform(-40, 40), rng.uniform(-40, 40), rng.uniform(-30, 30)]))[0]
        R = R_face.T @ tilt
        rotations.append(R)
        translations.append(position - R @ middle)
    return np.stack(rotations), np.stack(translations)


def drawn_fisheye_rig(board: BoardSpec = FISHEYE_BOARD, *, seed: int = 0, cameras: int = 3, instants: int = 40,
                      size: tuple[int, int] = (1024, 768), condition: str = "good",
                      supersample: int = 2) -> tuple[DrawnRig, list[list[np.ndarray]]]:
    """Draw ``instants`` views of ``board`` through a rig of ``cameras`` fisheye cameras (module docstring): the
    truth and frames, and per camera per instant the IDs of the corners the view shows (`visible_corners`)."""
    rng = np.random.default_rng(seed)
    intrinsics, rotations, translations = fisheye_cameras(rng, cameras, size)
    centres = np.stack([-R.T @ t for R, t in zip(rotations, translations)])
    board_r, board_t = fisheye_board_poses(rng, board, centres.mean(0), instants)
    noise = np.random.default_rng([seed, 1])
    frames, visible = [], []
    for camera, R, t in zip(intrinsics, rotations, translations):
        rays = supersampled_rays(camera, supersample)
        views, shown = [], []
        for R_b, t_b in zip(board_r, board_t):
            rotation, translation = R @ R_b, R @ t_b + t
            image = render_fisheye_view(board, camera, cv2.Rodrigues(rotation)[0], translation, rays=rays)
            views.append(degrade(image, condition, noise))
            shown.append(visible_corners(board, camera, rotation, translation))
        frames.append(views)
        visible.append(shown)
    return DrawnRig(board, intrinsics, rotations, translations, board_r, board_t, frames), visible
