"""Read the ArUco marker in a chessboard square, and match it against a board's own markers.

Given a homography from a square's unit frame to the image, the marker's bit cells are known
exactly: its (n + 2) x (n + 2) grid (one black border cell each side, as OpenCV prints) fills
the centred ``marker_length / square_length`` of the square. Each bit is the mean of a few
bilinear samples over the middle of its cell, so a dark or noisy image still gives usable
bits where thresholding single pixels (OpenCV's route) fails. A square counts as readable
when the white paper ring between marker and square edge is brighter than the marker's black
border (a black chessboard square is not).

Matching: the normalised cross-correlation (NCC) of the n x n inner bit means with the
expected bits of every marker of the board, in each of the four quarter turns that map the
board's square frame onto the cell's (see `lattice`). NCC ignores brightness and contrast,
and under blur the right marker still correlates best although no single bit can be
thresholded; each read proposes its few best (marker, turn) pairs and the board's geometry
decides among them (`placement`).

Square frame: (x, y) in [0, 1]^2, x along the board's X (right), y along its Y (down).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import cv2
import numpy as np

from deepcharuco.board import BoardSpec

SAMPLES_PER_BIT = 2  # per side: 4 bilinear samples over the middle half of each bit cell
BIT_FILL = 0.5  # the samples span this fraction of a bit cell (its edges blur into the neighbours)
# Grey levels between paper ring and marker border below which a square is unreadable. At the paper's
# darkness k = 9 white paper is ~2.5 grey levels: 2.0 lost those frames. Chosen on synthetic validation views
# (6x6 AprilTag and 5x4 DICT_4X4_100 boards, sensor noise; not the report's frames): 1.0 and 0.5 read k = 10
# alike, and no more scikit-image photos gave corners; the larger is kept.
MIN_CONTRAST = 1.0
PROPOSALS_PER_READ = 2  # a blurred read's right marker is often second best, rarely third
MIN_NCC = 0.3  # below this a (marker, turn) explains a read no better than a random board marker would

# Quarter turns: (x, y) in the board's square frame -> (u, v) in the cell's unit square.
QUARTER_TURNS = np.array([
    [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
    [[0, -1, 1], [1, 0, 0], [0, 0, 1]],
    [[-1, 0, 1], [0, -1, 1], [0, 0, 1]],
    [[0, 1, 0], [-1, 0, 1], [0, 0, 1]],
], np.float64)


@dataclass(frozen=True)
class BoardMarkers:
    """A board's markers as expected bits. ``ids``: (M,) marker IDs; ``squares``: (M, 2) int (column, row)
    of each marker's square; ``bits``: (M, 4, n, n) bool, True = white, the inner bits as read in a cell
    frame turned by 0..3 quarter turns (`QUARTER_TURNS`); ``ratio``: marker side / square side."""

    ids: np.ndarray
    squares: np.ndarray
    bits: np.ndarray
    ratio: float

    @property
    def size(self) -> int:
        """Inner bits per side (n)."""
        return self.bits.shape[-1]


@cache
def board_markers(board: BoardSpec) -> BoardMarkers:
    """The expected bits of every marker of ``board`` in each quarter turn (cached per board)."""
    ids, corners = board.marker_corners()
    dictionary = board.cv_dictionary()
    size = dictionary.markerSize
    grid = size + 2
    squares = np.floor(corners[:, :, :2].mean(axis=1) / board.square_length).astype(np.int64)
    centres = (np.arange(size) + 1.5) / grid  # inner bit centres in the marker's frame, 0..1
    u, v = np.meshgrid(centres, centres)  # u: column, v: row, in the cell frame
    cell_points = np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    expected = np.zeros((len(ids), 4, size, size), bool)
    for marker, marker_id in enumerate(ids):
        image = cv2.aruco.generateImageMarker(dictionary, int(marker_id), grid, borderBits=1) > 127
        for turn in range(4):
            # A bit read at (u, v) in the cell shows the board's marker at (x, y) = turn^-1 (u, v).
            x, y, _ = np.linalg.inv(QUARTER_TURNS[turn]) @ cell_points
            rows, cols = np.floor(y * grid).astype(int), np.floor(x * grid).astype(int)
            expected[marker, turn] = image[rows, cols].reshape(size, size)
    ratio = board.marker_length / board.square_length
    return BoardMarkers(ids=ids, squares=squares, bits=expected, ratio=ratio)


def _sample_grid(size: int, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Sample points in a square's unit frame: (G*G, S, 2) over the marker's (n + 2)^2 bit cells and
    (R, 2) on the paper ring around the marker. G = n + 2, S = SAMPLES_PER_BIT^2."""
    grid = size + 2
    cell = ratio / grid
    start = 0.5 - ratio / 2
    offsets = (np.arange(SAMPLES_PER_BIT) + 0.5) / SAMPLES_PER_BIT - 0.5
    offsets = offsets * BIT_FILL * cell
    ox, oy = np.meshgrid(offsets, offsets)
    centres = start + (np.arange(grid) + 0.5) * cell
    cx, cy = np.meshgrid(centres, centres)  # row-major: bit (row, col)
    bits = np.stack([cx.ravel()[:, None] + ox.ravel(), cy.ravel()[:, None] + oy.ravel()], axis=2)
    # The paper ring: halfway between the marker's edge and the square's, 8 points a side.
    ring_at = start / 2
    along = 0.5 - ratio / 2 + (np.arange(8) + 0.5) / 8 * ratio
    ring = np.concatenate([
        np.stack([along, np.full(8, ring_at)], 1), np.stack([along, np.full(8, 1 - ring_at)], 1),
        np.stack([np.full(8, ring_at), along], 1), np.stack([np.full(8, 1 - ring_at), along], 1),
    ])
    return bits, ring


def read_squares(gray: np.ndarray, homographies: np.ndarray, size: int, ratio: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Read the marker bits of R squares.

    Args:
        gray: (H, W) uint8 image in the board's canonical appearance (black ink on white paper).
        homographies: (R, 3, 3) each square's unit frame -> image pixels.
        size: inner bits per side (n); ratio: marker side / square side.

    Returns:
        (bits (R, n, n) float32 mean grey level of each inner bit, contrast (R,) float32 grey levels
        between the paper ring and the marker's border; 0 where the square is unreadable).
    """
    count = len(homographies)
    grid = size + 2
    if count == 0:
        return np.zeros((0, size, size), np.float32), np.zeros(0, np.float32)
    bit_points, ring_points = _sample_grid(size, ratio)
    local = np.concatenate([bit_points.reshape(-1, 2), ring_points])  # (P, 2)
    homographies = np.asarray(homographies, np.float64)
    # A square whose four corners lie in front of the camera and inside the image holds all its samples.
    unit = np.array([[0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], np.float64)
    corners = unit @ homographies.transpose(0, 2, 1)  # (R, 4, 3)
    height, width = gray.shape
    with np.errstate(divide="ignore", invalid="ignore"):
        corner_xy = corners[:, :, :2] / corners[:, :, 2:]
    inside = (corners[:, :, 2] > 0).all(axis=1) & np.isfinite(corner_xy).all(axis=(1, 2)) \
        & (corner_xy >= 0).all(axis=(1, 2)) & (corner_xy[:, :, 0] <= width - 1).all(axis=1) \
        & (corner_xy[:, :, 1] <= height - 1).all(axis=1)
    mapped = np.c_[local, np.ones(len(local))].astype(np.float32) @ homographies[inside].astype(np.float32).transpose(0, 2, 1)
    image_points = (mapped[:, :, :2] / mapped[:, :, 2:]).astype(np.float32)
    values = np.zeros((count, len(local)), np.float32)
    if inside.any():
        values[inside] = _sample(gray, image_points.reshape(-1, 2)).reshape(image_points.shape[:2])
    samples = bit_points.shape[1]
    bits = values[:, :grid * grid * samples].reshape(count, grid, grid, samples).mean(axis=3)
    ring = values[:, grid * grid * samples:]
    border = np.concatenate([bits[:, 0, :], bits[:, -1, :], bits[:, 1:-1, 0], bits[:, 1:-1, -1]], axis=1)
    dark = np.median(border, axis=1)
    bright = np.median(ring, axis=1)
    contrast = bright - dark
    readable = (contrast >= MIN_CONTRAST) & inside
    return bits[:, 1:-1, 1:-1].astype(np.float32), np.where(readable, contrast, 0.0).astype(np.float32)


def _sample(gray: np.ndarray, points: np.ndarray, row: int = 4096) -> np.ndarray:
    """(H, W) image, (P, 2) float32 x, y -> (P,) float32 bilinear samples. ``cv2.remap`` maps take at most
    32767 rows or columns: the points go through as rows of ``row``."""
    count = len(points)
    padded = np.zeros((-(-count // row) * row, 2), np.float32)
    padded[:count] = points
    grid = padded.reshape(-1, row, 2)
    values = cv2.remap(gray, grid[:, :, 0], grid[:, :, 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return values.reshape(-1)[:count].astype(np.float32)


def _normalised(values: np.ndarray) -> np.ndarray:
    """(..., P) -> zero mean, unit norm along the last axis (all-equal rows stay zero)."""
    centred = values - values.mean(axis=-1, keepdims=True)
    norm = np.linalg.norm(centred, axis=-1, keepdims=True)
    return centred / np.where(norm > 1e-9, norm, 1.0)


def correlate(bits: np.ndarray, markers: BoardMarkers) -> np.ndarray:
    """(R, n, n) inner bit means -> (R, M, 4) NCC with each board marker in each quarter turn."""
    expected = _normalised(markers.bits.reshape(len(markers.ids) * 4, -1).astype(np.float64))
    read = _normalised(bits.reshape(len(bits), markers.size * markers.size).astype(np.float64))
    return (read @ expected.T).reshape(len(bits), len(markers.ids), 4)


@dataclass(frozen=True)
class MarkerMatches:
    """(marker, turn) proposals for the reads. ``read``: (K,) index of the read; ``marker``: (K,) index into
    `BoardMarkers` (not the marker ID); ``turn``: (K,) quarter turns from the board's square frame to the
    cell's; ``ncc``: (K,) correlation of the read with that marker in that turn."""

    read: np.ndarray
    marker: np.ndarray
    turn: np.ndarray
    ncc: np.ndarray


def match_markers(bits: np.ndarray, contrast: np.ndarray, markers: BoardMarkers,
                  per_read: int = PROPOSALS_PER_READ) -> MarkerMatches:
    """(R, n, n) bit means and (R,) contrasts -> each readable read's ``per_read`` best (marker, turn) pairs
    with NCC >= `MIN_NCC`, best first within a read."""
    readable = np.flatnonzero(contrast > 0)
    ncc = correlate(bits[readable], markers).reshape(len(readable), len(markers.ids) * 4)
    per_read = min(per_read, ncc.shape[1])
    best = np.argpartition(-ncc, per_read - 1, axis=1)[:, :per_read] if per_read < ncc.shape[1] \
        else np.tile(np.arange(ncc.shape[1]), (len(ncc), 1))
    best = np.take_along_axis(best, np.argsort(-np.take_along_axis(ncc, best, axis=1), axis=1, kind="stable"), axis=1)
    rows = np.repeat(np.arange(len(readable)), per_read)
    flat = best.ravel()
    score = ncc[rows, flat] if len(rows) else np.zeros(0)
    keep = score >= MIN_NCC
    return MarkerMatches(read=readable[rows[keep]], marker=flat[keep] // 4, turn=flat[keep] % 4, ncc=score[keep])
