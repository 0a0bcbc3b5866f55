"""Drawn videos of a board waved in front of a still 1280x720 webcam, with exact truth in every frame: the validation
videos the tracker's settings are chosen on (`benchmarks/search_every.py`); the real videos in realdata/ measure them.

No renderer: each frame is the board drawn exactly (`realistic.board_layer`) over one still
cluttered background (`realistic.clutter`). A video is visits of the board with empty stretches of 5-40 frames
between them and before the first. A visit enters across an edge of the frame, is waved through two or three places
and leaves across an edge. At each place its squares are 8-90 px wide (log-uniform: a board across the room or at
arm's length), tilted up to 50 degrees and rolled up to 30. It moves between places in 6-30 frames, eased in and out.

Conditions:
- ``good``: sensor noise of 2 grey levels;
- ``dark``: the light x `DARKNESS_BASE` ** 7 (~3 %), then the same noise;
- ``shake``: each frame's board smeared along its own image motion over half the frame interval (a 1/60 s
  exposure at 30 fps), over the still background; then the noise.

Every random choice comes from ``seed``; a seed's board moves alike under every condition.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.boards.synthetic import look_at_pose
from deepcharuco.geometry.pose import project_corners
from evaluate.paper.protocols import DARKNESS_BASE
from evaluate.speed.realistic import board_layer, clutter, webcam_K

CONDITIONS = ("good", "dark", "shake")
SIZE = (1280, 720)
SQUARE_PX = (8.0, 90.0)  # a square's side at a place, log-uniform
MAX_TILT_DEG, MAX_ROLL_DEG = 50.0, 30.0
GAP_FRAMES = (5, 40)  # without the board, between visits and before the first
MOVE_FRAMES = (6, 30)  # from one place to the next
EXPOSURE = 0.5  # of the frame interval: a shaken board's smear is half its motion between frames
NOISE = 2.0  # grey levels
MIN_VISIBLE = 6  # corners in the frame for a frame to count as showing the board


@dataclass
class DrawnVideo:
    """``frames[n]``: (H, W) uint8; ``corners[n]``: (N, 2) float32 truth of every corner (OpenCV pixel centres, also
    outside the frame); ``visible[n]``: (N,) bool, inside the frame by a pixel; None for both where no board is
    drawn; ``smear[n]``: the length (px) the board is smeared over (0 but in ``shake``): along it a corner is a ramp,
    and where on it a detector puts the corner is a matter of definition, not an error."""

    board: BoardSpec
    condition: str
    frames: list[np.ndarray]
    corners: list[np.ndarray | None]
    visible: list[np.ndarray | None]
    smear: list[float]

    def shows_board(self, index: int) -> bool:
        """Whether frame ``index`` shows at least `MIN_VISIBLE` corners."""
        return self.visible[index] is not None and int(self.visible[index].sum()) >= MIN_VISIBLE


@dataclass(frozen=True)
class _Place:
    """Where the board is: its centre's image position (px), distance (m), tilts and roll (degrees)."""

    u: float
    v: float
    distance: float
    tilt_x: float
    tilt_y: float
    roll: float


def _place(board: BoardSpec, K: np.ndarray, size: tuple[int, int], rng: np.random.Generator) -> _Place:
    """A place inside the frame: the centre in the middle 70 % of each side."""
    width, height = size
    square_px = math.exp(rng.uniform(math.log(SQUARE_PX[0]), math.log(SQUARE_PX[1])))
    distance = K[0, 0] * board.square_length / square_px
    u, v = rng.uniform(0.15, 0.85) * width, rng.uniform(0.15, 0.85) * height
    return _Place(u, v, distance, rng.uniform(-MAX_TILT_DEG, MAX_TILT_DEG), rng.uniform(-MAX_TILT_DEG, MAX_TILT_DEG),
                  rng.uniform(-MAX_ROLL_DEG, MAX_ROLL_DEG))


def _outside(place: _Place, board: BoardSpec, K: np.ndarray, size: tuple[int, int], rng: np.random.Generator
             ) -> _Place:
    """``place`` moved straight across a random edge until the whole board is beyond it."""
    width, height = size
    reach = 0.75 * K[0, 0] * math.hypot(*board.size_m) / place.distance + 10  # px from centre to the sheet's edge
    edge = int(rng.integers(4))
    u, v = place.u, place.v
    if edge == 0:
        u = -reach
    elif edge == 1:
        u = width - 1 + reach
    elif edge == 2:
        v = -reach
    else:
        v = height - 1 + reach
    return _Place(u, v, place.distance, place.tilt_x, place.tilt_y, place.roll)


def _between(a: _Place, b: _Place, t: float) -> _Place:
    """Eased (smoothstep) from ``a`` at t = 0 to ``b`` at t = 1; the distance in log."""
    s = t * t * (3 - 2 * t)
    mix = lambda x, y: x + (y - x) * s  # noqa: E731 - one expression, used six times
    return _Place(mix(a.u, b.u), mix(a.v, b.v), math.exp(mix(math.log(a.distance), math.log(b.distance))),
                  mix(a.tilt_x, b.tilt_x), mix(a.tilt_y, b.tilt_y), mix(a.roll, b.roll))


def _pose(place: _Place, board: BoardSpec, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    offset = ((place.u - K[0, 2]) * place.distance / K[0, 0], (place.v - K[1, 2]) * place.distance / K[1, 1])
    return look_at_pose(board, place.distance, place.tilt_x, place.tilt_y, place.roll, offset)


def _trajectory(board: BoardSpec, K: np.ndarray, size: tuple[int, int], frames: int, rng: np.random.Generator
                ) -> list[_Place | None]:
    """Each frame's place, None where no board is drawn (module docstring)."""
    places: list[_Place | None] = []
    while len(places) < frames:
        places += [None] * int(rng.integers(GAP_FRAMES[0], GAP_FRAMES[1] + 1))
        inside = [_place(board, K, size, rng) for _ in range(int(rng.integers(2, 4)))]
        route = [_outside(inside[0], board, K, size, rng), *inside, _outside(inside[-1], board, K, size, rng)]
        for a, b in zip(route, route[1:]):
            steps = int(rng.integers(MOVE_FRAMES[0], MOVE_FRAMES[1] + 1))
            places += [_between(a, b, i / steps) for i in range(steps)]
    return places[:frames]


def _smear_kernel(motion: np.ndarray) -> np.ndarray | None:
    """A normalised line kernel along ``motion`` (px), centred (its centroid at the kernel's centre: the truth does
    not move), or None for less than a pixel."""
    length = float(np.hypot(*motion))
    if length < 1.0:
        return None
    half = int(math.ceil(length / 2)) + 1
    kernel = np.zeros((2 * half + 1, 2 * half + 1), np.float32)
    for t in np.linspace(-0.5, 0.5, max(2, int(4 * length))):
        x, y = half + t * motion[0], half + t * motion[1]
        x0, y0 = int(math.floor(x)), int(math.floor(y))
        fx, fy = x - x0, y - y0
        kernel[y0, x0] += (1 - fx) * (1 - fy)
        kernel[y0, x0 + 1] += fx * (1 - fy)
        kernel[y0 + 1, x0] += (1 - fx) * fy
        kernel[y0 + 1, x0 + 1] += fx * fy
    return kernel / kernel.sum()


def drawn_video(board: BoardSpec, *, seed: int, frames: int = 150, condition: str = "good",
                size: tuple[int, int] = SIZE, supersample: int = 2) -> DrawnVideo:
    """A video of ``frames`` frames of ``board`` under ``condition`` (module docstring), drawn from ``seed``."""
    if condition not in CONDITIONS:
        raise ValueError(f"condition must be one of {', '.join(CONDITIONS)}, got {condition!r}")
    rng = np.random.default_rng(seed)  # the scene: the same motion under every condition
    noise = np.random.default_rng([seed, CONDITIONS.index(condition)])
    K = webcam_K(size)
    background = clutter(rng, size).astype(np.float32)
    places = _trajectory(board, K, size, frames, rng)
    width, height = size
    video = DrawnVideo(board, condition, [], [], [], [])
    gain = 1.0
    for index, place in enumerate(places):
        smear = 0.0
        if place is None:
            image = background.copy()
            video.corners.append(None)
            video.visible.append(None)
        else:
            if index == 0 or places[index - 1] is None:
                gain = rng.uniform(0.6, 1.0)  # each visit lit its own way
            rvec, tvec = _pose(place, board, K)
            drawn, coverage = board_layer(board, K, rvec, tvec, size, supersample)
            drawn *= gain
            motion = EXPOSURE * _motion(places, index) if condition == "shake" else np.zeros(2)
            kernel = _smear_kernel(motion)
            if kernel is not None:
                smear = float(np.hypot(*motion))
                drawn = cv2.filter2D(drawn, -1, kernel, borderType=cv2.BORDER_CONSTANT)
                coverage = cv2.filter2D(coverage, -1, kernel, borderType=cv2.BORDER_CONSTANT)
            image = drawn + background * (1 - coverage)
            corners = project_corners(board, rvec, tvec, K).astype(np.float32)
            video.corners.append(corners)
            video.visible.append((corners[:, 0] >= 1) & (corners[:, 0] <= width - 2) & (corners[:, 1] >= 1)
                                 & (corners[:, 1] <= height - 2))
        video.smear.append(smear)
        if condition == "dark":
            image = image * DARKNESS_BASE ** 7
        image = image + noise.normal(0, NOISE, image.shape).astype(np.float32)
        video.frames.append(np.clip(np.rint(image), 0, 255).astype(np.uint8))
    return video


def _motion(places: list[_Place | None], index: int) -> np.ndarray:
    """The board centre's image motion (px a frame) at frame ``index``: from the frame before to the frame after,
    halved (one-sided at a visit's ends)."""
    here = places[index]
    before = places[index - 1] if index > 0 else None
    after = places[index + 1] if index + 1 < len(places) else None
    steps = (before is not None) + (after is not None)
    if steps == 0:
        return np.zeros(2)
    a, b = before or here, after or here
    return np.array([b.u - a.u, b.v - a.v]) / steps
