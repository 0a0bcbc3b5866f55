"""Drawn views of a board waved through a rig of cameras with known intrinsics, lens distortion and poses.

No renderer: each camera's view is the board drawn exactly (`deepcharuco.boards.synthetic.render_board_view`) through
a wider pinhole camera and resampled into the distorted image (`datagen.lens.distort_image`), so a corner lies
where ``cv2.projectPoints`` with the camera's (K, dist) and pose puts it. Conditions: ``good`` (sensor noise of
2 grey levels), ``dark`` (the light scaled by `DARKNESS_BASE` ** 7, then the same noise: ~3 % of the light, a
white print at ~8 grey levels) and ``shake`` (each instant blurred along a random direction by 5-11 px, as a
board waved fast). Every random choice comes from ``seed``.

The rig: ``cameras`` cameras on an arc 0.25-0.45 m apart (the first at the origin looking down +z), all toward a
point 1.1-1.4 m ahead; the board is waved through a 1.0 x 0.7 x 0.6 m volume around it (as a user covers
every camera's image), tilted up to 40 degrees
toward or away from the cameras.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from datagen.lens import distort_image, distortion_maps, wide_camera
from deepcharuco.boards.board import BoardSpec
from deepcharuco.boards.synthetic import render_board_view
from deepcharuco.geometry.camera import Camera
from evaluate.paper.protocols import DARKNESS_BASE

CONDITIONS = ("good", "dark", "shake")
# The rigs' board: an A2-sized 9 x 6 board of 60 mm squares, as rigs covering a room use.
RIG_BOARD = BoardSpec(squares_x=9, squares_y=6, square_length=0.06, marker_length=0.045, dictionary="DICT_6X6_250")


@dataclass
class DrawnRig:
    """The truth and the frames: ``frames[c][n]`` is camera c's (H, W) uint8 view at instant n."""

    board: BoardSpec
    cameras: list[Camera]
    rotations: np.ndarray  # (C, 3, 3): x_cam = R X + t, X in camera 0's frame
    translations: np.ndarray  # (C, 3) metres
    board_rotations: np.ndarray  # (N, 3, 3) board -> camera 0's frame
    board_translations: np.ndarray  # (N, 3)
    frames: list[list[np.ndarray]]

    def save_frames(self, root: Path) -> list[Path]:
        """Write ``root/cam<c>/<instant>.png`` per camera (the folders `deepcharuco calibrate` takes as a rig's
        sources); returns the cameras' folders."""
        folders = []
        for c, frames in enumerate(self.frames):
            folder = Path(root) / f"cam{c}"
            folder.mkdir(parents=True, exist_ok=True)
            for n, image in enumerate(frames):
                cv2.imwrite(str(folder / f"{n:03d}.png"), image)
            folders.append(folder)
        return folders

    @property
    def baseline(self) -> float:
        """The largest distance between two cameras' centres (metres)."""
        centres = [-R.T @ t for R, t in zip(self.rotations, self.translations)]
        return max(float(np.linalg.norm(a - b)) for a in centres for b in centres)


def look_at(eye: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of a camera at ``eye`` looking at ``target`` (y down), x_cam = R X + t."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(np.array([0.0, 1.0, 0.0]), z)  # the image's y points down the world's y
    x = x / np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return R, -R @ eye


def rig_cameras(rng: np.random.Generator, count: int, size: tuple[int, int]) -> tuple[list[Camera], np.ndarray, np.ndarray, np.ndarray]:
    """``count`` cameras (intrinsics, rotations, translations) and the point they look at."""
    target = np.array([0.0, 0.0, rng.uniform(1.1, 1.4)])
    width, height = size
    cameras, rotations, translations = [], [], []
    angle = 0.0
    for c in range(count):
        hfov = math.radians(rng.uniform(55, 75))
        fx = width / 2 / math.tan(hfov / 2)
        K = np.array([[fx, 0, (width - 1) / 2 + rng.uniform(-12, 12)],
                      [0, fx * rng.uniform(0.995, 1.005), (height - 1) / 2 + rng.uniform(-10, 10)], [0, 0, 1.0]])
        k1 = rng.uniform(-0.35, 0.05)
        cameras.append(Camera(K, np.array([k1, k1 * k1 * rng.uniform(0.5, 1.0), 0.0, 0.0, 0.0]), size))
        if c == 0:
            rotations.append(np.eye(3))
            translations.append(np.zeros(3))
            continue
        # Alternate sides, each farther round the arc about the target.
        angle = (abs(angle) + math.atan2(rng.uniform(0.25, 0.45), target[2])) * (1 if c % 2 else -1)
        eye = target + target[2] * np.array([math.sin(angle), rng.uniform(-0.1, 0.1), -math.cos(angle)])
        R, t = look_at(eye, target)
        rotations.append(R)
        translations.append(t)
    return cameras, np.stack(rotations), np.stack(translations), target


def board_poses(rng: np.random.Generator, board: BoardSpec, target: np.ndarray, count: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """``count`` board poses (board -> camera 0's frame) around ``target``, facing the rig, tilted up to 40 deg."""
    centre = np.array([board.size_m[0] / 2, board.size_m[1] / 2, 0.0])
    rotations, translations = [], []
    for _ in range(count):
        tilt = np.radians(rng.uniform(-40, 40, 2))
        roll = np.radians(rng.uniform(-30, 30))
        # The board's z axis points away from the cameras (its printed face toward them).
        R = cv2.Rodrigues(np.array([tilt[0], tilt[1], 0.0]))[0] @ cv2.Rodrigues(np.array([0.0, 0.0, roll]))[0]
        position = target + np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.35, 0.35), rng.uniform(-0.4, 0.2)])
        rotations.append(R)
        translations.append(position - R @ centre)
    return np.stack(rotations), np.stack(translations)


def degrade(image: np.ndarray, condition: str, rng: np.random.Generator) -> np.ndarray:
    """``image`` under ``condition`` (module docstring), with sensor noise."""
    light = image.astype(np.float32)
    if condition == "shake":
        length = int(rng.integers(5, 12))
        angle = rng.uniform(0, 180)
        kernel = np.zeros((length, length), np.float32)
        kernel[length // 2, :] = 1.0
        kernel = cv2.warpAffine(kernel, cv2.getRotationMatrix2D(((length - 1) / 2, (length - 1) / 2), angle, 1.0),
                                (length, length))
        light = cv2.filter2D(light, -1, kernel / kernel.sum(), borderType=cv2.BORDER_REFLECT)
    elif condition == "dark":
        light = light * DARKNESS_BASE ** 7
    elif condition != "good":
        raise ValueError(f"condition must be one of {CONDITIONS}, got {condition!r}")
    noisy = light + rng.normal(0.0, 2.0, light.shape).astype(np.float32)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def drawn_rig(board: BoardSpec, *, seed: int = 0, cameras: int = 3, instants: int = 40, size: tuple[int, int] = (640, 480),
              condition: str = "good") -> DrawnRig:
    """Draw ``instants`` views of ``board`` through a rig of ``cameras`` cameras (module docstring)."""
    rng = np.random.default_rng(seed)
    intrinsics, rotations, translations, target = rig_cameras(rng, cameras, size)
    board_r, board_t = board_poses(rng, board, target, instants)
    noise = np.random.default_rng([seed, 1])
    frames: list[list[np.ndarray]] = []
    for camera, R, t in zip(intrinsics, rotations, translations):
        K_wide, wide_size = wide_camera(camera.K, camera.dist, size)
        maps = distortion_maps(camera.K, camera.dist, size, K_wide)
        views = []
        for R_b, t_b in zip(board_r, board_t):
            rotation, translation = R @ R_b, R @ t_b + t
            wide = render_board_view(board, K_wide, cv2.Rodrigues(rotation)[0].ravel(), translation, wide_size,
                                     supersample=2)
            views.append(degrade(distort_image(wide, camera.K, camera.dist, size, K_wide, maps=maps), condition, noise))
        frames.append(views)
    return DrawnRig(board, intrinsics, rotations, translations, board_r, board_t, frames)
