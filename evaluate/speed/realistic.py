"""Frames a user points a camera at, for timing and scoring detectors: a board drawn into a cluttered
background at a chosen share of the frame's width (exact truth), frames without any board, and every
frame of real videos.

Backgrounds are procedural clutter (`clutter`: shapes, lines, text, tiled grids that look like corners,
an uneven light, sensor noise) or real frames with no board in them (`real_backgrounds`: the caliscope
webcams' frames marked "no" in their review). Boards are drawn by `deepcharuco.boards.synthetic` (exact
to well under 0.1 px) and laid into the background by their own coverage, so the board's edge blends as
a sensor would see it. Every random choice comes from the ``rng`` passed in.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.boards.synthetic import look_at_pose, render_board_view
from deepcharuco.geometry.pose import project_corners
from evaluate.captures.reader import REVIEW_FILE, VIDEO_SUFFIXES, Medium, read_review
from evaluate.captures.reader import video_frames as capture_video_frames
from evaluate.paper.protocols import TestFrame

WORDS = ("ACME", "exit", "42", "calibration", "Tuesday", "#7", "warning", "lab B", "0.5 mm", "ok")


def clutter(rng: np.random.Generator, size: tuple[int, int]) -> np.ndarray:
    """(H, W) uint8 procedural clutter of ``size`` (W, H): an uneven light, filled shapes, lines, text and
    tiled grids (shelves, keyboards, tiles: corner-like junctions that are not a board), blurred by a lens and
    with sensor noise."""
    width, height = size
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    gx, gy = rng.uniform(-0.4, 0.4, 2)
    image = 110 + 60 * (gx * (xx / width - 0.5) + gy * (yy / height - 0.5)) + np.zeros((height, width), np.float32)
    scale = max(width, height) / 640
    for _ in range(int(rng.integers(25, 45))):
        colour = float(rng.uniform(10, 245))
        kind = rng.integers(0, 5)
        centre = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        extent = int(rng.uniform(8, 120) * scale)
        if kind == 0:
            cv2.rectangle(image, centre, (centre[0] + extent, centre[1] + int(rng.uniform(0.3, 2) * extent)), colour, -1)
        elif kind == 1:
            cv2.ellipse(image, centre, (extent, int(rng.uniform(0.3, 1) * extent)), float(rng.uniform(0, 180)),
                        0, 360, colour, -1)
        elif kind == 2:
            end = (centre[0] + int(rng.normal(0, 2 * extent)), centre[1] + int(rng.normal(0, 2 * extent)))
            cv2.line(image, centre, end, colour, max(1, int(rng.uniform(1, 4) * scale)))
        elif kind == 3:
            # drawn as a uint8 mask: OpenCV 5's putText takes 8-bit images only (the same pixels as 4.x's float)
            mask = np.zeros((height, width), np.uint8)
            cv2.putText(mask, str(rng.choice(WORDS)), centre, cv2.FONT_HERSHEY_SIMPLEX, float(rng.uniform(0.4, 1.5) * scale),
                        255, max(1, int(2 * scale)))
            image[mask > 0] = colour
        else:  # a tiled grid: dark gaps between light tiles, seen at an angle
            _tiled_grid(image, rng, centre, extent, colour)
    image = cv2.GaussianBlur(image, (0, 0), 0.8)
    image += rng.normal(0, 3.0, image.shape).astype(np.float32)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def _tiled_grid(image: np.ndarray, rng: np.random.Generator, centre: tuple[int, int], extent: int, colour: float) -> None:
    tiles = int(rng.integers(3, 8))
    pitch = max(4, extent // tiles)
    tile = np.full((tiles * pitch, tiles * pitch), colour, np.float32)
    gap = max(1, pitch // 6)
    for i in range(tiles):
        tile[i * pitch:i * pitch + gap, :] = colour * 0.3
        tile[:, i * pitch:i * pitch + gap] = colour * 0.3
    angle = float(rng.uniform(0, 90))
    matrix = cv2.getRotationMatrix2D((tile.shape[1] / 2, tile.shape[0] / 2), angle, 1.0)
    matrix[:, 2] += np.array(centre, np.float64) - np.array(tile.shape[::-1]) / 2
    mask = cv2.warpAffine(np.ones_like(tile), matrix, image.shape[::-1])
    warped = cv2.warpAffine(tile, matrix, image.shape[::-1])
    image[:] = image * (1 - mask) + warped * mask


def real_backgrounds(folder: Path, limit: int | None = None) -> list[np.ndarray]:
    """Grey frames with no board in them from a capture folder's videos: the frames its review
    (``frames_review.csv``, read by `evaluate.captures.reader.read_review`) marks ``board_visible == "no"``;
    at most ``limit`` of them, spread over the videos. [] where the folder lacks the review."""
    review = folder / REVIEW_FILE
    if not review.is_file():
        return []
    media = [Medium(path, "video") for path in sorted(folder.iterdir()) if path.suffix.lower() in VIDEO_SUFFIXES]
    wanted: dict[str, list[int]] = {}
    for name, verdict in read_review(review, media).items():
        video, _, number = name.partition("#")
        if verdict == "no" and number:
            wanted.setdefault(video, []).append(int(number))
    frames = []
    for video, numbers in sorted(wanted.items()):
        if limit is not None:
            numbers = numbers[:: max(1, len(numbers) * len(wanted) // limit)]
        keep = set(numbers)
        frames.extend(gray for index, gray in capture_video_frames(folder / video, 1, None) if index in keep)
    return frames[:limit] if limit is not None else frames


def video_frames(path: Path) -> list[np.ndarray]:
    """Every frame of a video as (H, W) uint8 grey (`evaluate.captures.reader.video_frames`: a damaged stretch is
    skipped and said)."""
    return [gray for _, gray in capture_video_frames(path, 1, None)]


@dataclass(frozen=True)
class Placement:
    """How a board is drawn in: its width as a share of the frame's (``low``-``high``), tilt and roll ranges."""

    low: float
    high: float
    tilt_deg: float = 35.0
    roll_deg: float = 30.0


def webcam_K(size: tuple[int, int]) -> np.ndarray:
    """(3, 3) K of the frames drawn here, ``size`` (W, H): a webcam's focal length, 0.9 x the width (~58 degrees
    across), the principal point at the centre (OpenCV pixel centres)."""
    width, height = size
    focal = 0.9 * width
    return np.array([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1.0]])


def with_board(board: BoardSpec, background: np.ndarray, rng: np.random.Generator, placement: Placement,
               name: str = "") -> TestFrame:
    """``background`` (H, W) uint8 with ``board`` drawn into it, wholly inside the frame, its width about a
    ``placement`` share of the frame's (less where a board that wide would not fit), lit by a random gain (a board in the shade of a brighter room), and
    sensor noise over everything. Truth: the projected corners (OpenCV pixel centres), pose and K."""
    height, width = background.shape
    K = webcam_K((width, height))
    focal = K[0, 0]
    board_width = max(board.size_m)
    share = rng.uniform(placement.low, placement.high)
    for _ in range(200):
        share *= 0.98  # until it fits: a square board never fills 95 % of a 4:3 frame's width
        distance = focal * board_width / (share * width)
        tilt = rng.uniform(-placement.tilt_deg, placement.tilt_deg, 2)
        roll = rng.uniform(-placement.roll_deg, placement.roll_deg)
        # the board's centre anywhere its drawn extent fits: offsets in metres at its distance
        reach = 0.5 * (np.array([width, height]) - share * width) * distance / focal
        offset = tuple(rng.uniform(-1, 1, 2) * np.maximum(reach, 0))
        rvec, tvec = look_at_pose(board, distance, tilt[0], tilt[1], roll, offset)
        outline = _outline(board, K, rvec, tvec)
        if (outline >= 2).all() and (outline[:, 0] <= width - 3).all() and (outline[:, 1] <= height - 3).all():
            break
    else:
        raise ValueError(f"a {board.squares_x}x{board.squares_y} board does not fit a {width}x{height} frame at "
                         f"{placement.low:.0%}-{placement.high:.0%} of its width")
    supersample = 4 if width * height <= 1280 * 720 else 2
    drawn, coverage = board_layer(board, K, rvec, tvec, (width, height), supersample)
    gain = rng.uniform(0.55, 1.0)
    image = drawn * gain + background.astype(np.float32) * (1 - coverage)
    image += rng.normal(0, 2.0, image.shape).astype(np.float32)
    image = np.clip(np.rint(image), 0, 255).astype(np.uint8)
    corners = project_corners(board, rvec, tvec, K).astype(np.float32)
    return TestFrame(image, corners, np.ones(len(corners), bool), K, np.ravel(rvec), np.ravel(tvec), name)


def board_layer(board: BoardSpec, K: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, size: tuple[int, int],
                supersample: int) -> tuple[np.ndarray, np.ndarray]:
    """The printed board drawn alone on black, and the share of each pixel its sheet covers: ((H, W) float32 grey
    levels, (H, W) float32 in [0, 1]). A frame is ``drawn * gain + background * (1 - coverage)``."""
    drawn = render_board_view(board, K, rvec, tvec, size, background=0, supersample=supersample)
    coverage = render_board_view(board, K, rvec, tvec, size, background=0, supersample=supersample,
                                 paint=lambda texture: np.full_like(texture.image, 255))
    return drawn.astype(np.float32), coverage.astype(np.float32) / 255


def _outline(board: BoardSpec, K: np.ndarray, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """(4, 2) image positions of the printed sheet's corners (half a square of paper around the grid)."""
    margin = 0.5 * board.square_length
    w, h = board.size_m
    sheet = np.array([[-margin, -margin, 0], [w + margin, -margin, 0], [-margin, h + margin, 0],
                      [w + margin, h + margin, 0]])
    points, _ = cv2.projectPoints(sheet, np.asarray(rvec, np.float64), np.asarray(tvec, np.float64), K, None)
    return points.reshape(-1, 2)


def without_board(background: np.ndarray, name: str = "") -> TestFrame:
    """A frame with no board: every corner a detector reports there is wrong."""
    height, width = background.shape
    return TestFrame(background, np.zeros((0, 2), np.float32), np.zeros(0, bool), webcam_K((width, height)), name=name)


def fit(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``image`` cropped to the aspect ratio of ``size`` (W, H) about its centre and resized to it."""
    width, height = size
    h, w = image.shape
    if w * height > h * width:
        keep = round(h * width / height)
        image = image[:, (w - keep) // 2:(w - keep) // 2 + keep]
    else:
        keep = round(w * height / width)
        image = image[(h - keep) // 2:(h - keep) // 2 + keep]
    interpolation = cv2.INTER_AREA if image.shape[1] > width else cv2.INTER_LINEAR
    return cv2.resize(image, (width, height), interpolation=interpolation)
