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

Two readers (``reader``, default `DEFAULT_READER`): "sampled" is the above; "learned" rectifies each
square onto its marker's bit grid (`rectify_squares`) and a small CNN (`networks.bit_reader`) gives
each bit a logit (white / black); a candidate marker scores the cosine of the bounded logits with
its bits (`correlate`), on NCC's scale, so the proposals, the placement vote and the final check are
the same for both. "sampled" stays the default: on the validation views of train/bit_reader.py both
readers score alike (blur k = 10: 0.916 each) and the learned one takes ~11x the time per square.

Square frame: (x, y) in [0, 1]^2, x along the board's X (right), y along its Y (down).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache, cached_property
from pathlib import Path

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.core.checks import check_choice
from deepcharuco.core.vectors import homogeneous
from deepcharuco.networks.shipped import WEIGHTS_DIR

try:  # the reads' loops compiled (pip install deepcharuco[fast]); else numpy's, the same values
    import deepcharuco.detection.markers.decode_kernel as compiled_kernel
except ImportError:
    compiled_kernel = None

SAMPLES_PER_BIT = 2  # per side: 4 bilinear samples over the middle half of each bit cell
BIT_FILL = 0.5  # the samples span this fraction of a bit cell (its edges blur into the neighbours)
# Grey levels between paper ring and marker border below which a square is unreadable. At the paper's
# darkness k = 9 white paper is ~2.5 grey levels: 2.0 lost those frames. Chosen on synthetic validation views
# (6x6 AprilTag and 5x4 DICT_4X4_100 boards, sensor noise; not the report's frames): 1.0 and 0.5 read k = 10
# alike, and no more scikit-image photos gave corners; the larger is kept.
MIN_CONTRAST = 1.0
PROPOSALS_PER_READ = 2  # a blurred read's right marker is often second best, rarely third
MIN_NCC = 0.3  # below this a (marker, turn) explains a read no better than a random board marker would
READERS = ("sampled", "learned")
DEFAULT_READER = "sampled"
BIT_READER_WEIGHTS = WEIGHTS_DIR / "bit_reader.pt"
# The learned reader's logits are bounded as tanh(logit / MAX_BIT_LOGIT) before scoring: no bit outvotes the
# others by more than a log-likelihood ratio of ~4 (p = 0.018 that a confident bit is wrong), so one smeared
# bit costs a marker a bounded amount.
MAX_BIT_LOGIT = 4.0

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

    @cached_property
    def normalised_bits(self) -> np.ndarray:
        """(M * 4, n * n) float64: each (marker, turn)'s bits centred and scaled to unit length, NCC's reference
        (`correlate`); made once per board, not once per read."""
        return _normalised(self.bits.reshape(len(self.ids) * 4, -1).astype(np.float64))


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


@cache
def _sample_grid(size: int, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Sample points in a square's unit frame: (G*G, S, 2) over the marker's (n + 2)^2 bit cells and
    (R, 2) on the paper ring around the marker. G = n + 2, S = SAMPLES_PER_BIT^2. Computed once per
    (size, ratio): the arrays are read-only."""
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
    bits.flags.writeable = ring.flags.writeable = False
    return bits, ring


def _reader(reader: str | None) -> str:
    reader = DEFAULT_READER if reader is None else reader
    check_choice("reader", reader, READERS)
    return reader


def _row_medians(values: np.ndarray) -> np.ndarray:
    """(R, n) -> (R,) each row's median, as ``np.median(values, axis=1)`` gives it (the mean of the two middle values
    for even n) at half its cost on these small rows."""
    half = values.shape[1] // 2
    if values.shape[1] % 2:
        return np.partition(values, half, axis=1)[:, half]
    middle = np.partition(values, [half - 1, half], axis=1)
    return (middle[:, half - 1] + middle[:, half]) / values.dtype.type(2)


def read_squares(gray: np.ndarray, homographies: np.ndarray, size: int, ratio: float, reader: str | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Read the marker bits of R squares.

    Args:
        gray: (H, W) uint8 image in the board's canonical appearance (black ink on white paper).
        homographies: (R, 3, 3) each square's unit frame -> image pixels.
        size: inner bits per side (n); ratio: marker side / square side.
        reader: "sampled" or "learned" (default `DEFAULT_READER`).

    Returns:
        (bits (R, n, n) float32: "sampled": mean grey level of each inner bit; "learned": tanh of each
        bit's logit (log-likelihood ratio white / black) over `MAX_BIT_LOGIT`, in (-1, 1);
        contrast (R,) float32 grey levels between the paper ring and the marker's border; 0 where the
        square is unreadable, whichever the reader).
    """
    reader = _reader(reader)
    bits, contrast = _sampled_reads(gray, homographies, size, ratio)
    if reader == "learned" and np.any(contrast > 0):
        readable = np.flatnonzero(contrast > 0)
        bits = np.zeros_like(bits)
        bits[readable] = learned_bits(gray, np.asarray(homographies, np.float64)[readable], size, ratio)
    return bits, contrast


def _sampled_reads(gray: np.ndarray, homographies: np.ndarray, size: int, ratio: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """`read_squares` with the "sampled" reader: every sample of every square through its homography
    (`_square_maps`), ONE ``cv2.remap`` for all of them, each square's cells, border and ring reduced
    (`_reduce_reads`); by `decode_kernel` where numba is installed, else numpy (the same values)."""
    count = len(homographies)
    grid = size + 2
    if count == 0:
        return np.zeros((0, size, size), np.float32), np.zeros(0, np.float32)
    bit_points, ring_points = _sample_grid(size, ratio)
    local = _local_points(size, ratio)  # (P, 2) float32
    homographies = np.asarray(homographies, np.float64)
    height, width = gray.shape
    compiled = compiled_kernel is not None
    inside = compiled_kernel.squares_inside(np.ascontiguousarray(homographies), width, height) if compiled else \
        _squares_inside(homographies, width, height)
    bits = np.zeros((count, grid, grid), np.float32)
    dark = np.zeros(count, np.float32)
    bright = np.zeros(count, np.float32)
    if inside.any():
        inner = np.ascontiguousarray(homographies[inside].astype(np.float32))
        x, y = compiled_kernel.square_maps(inner, local) if compiled else _square_maps(inner, local)
        values = sample_maps(gray, x, y)  # (R', P): rows of samples, one remap for all
        reduce = compiled_kernel.reduce_reads if compiled else _reduce_reads
        bits[inside], dark[inside], bright[inside] = reduce(values, grid, bit_points.shape[1])
    contrast = bright - dark
    readable = (contrast >= MIN_CONTRAST) & inside
    return bits[:, 1:-1, 1:-1].astype(np.float32), np.where(readable, contrast, 0.0).astype(np.float32)


def _squares_inside(homographies: np.ndarray, width: int, height: int) -> np.ndarray:
    """(R, 3, 3) float64 unit frames -> image -> (R,) bool: the square's four corners lie in front of the camera and
    inside a (``width``, ``height``) image, so all its samples do (`decode_kernel.squares_inside` computes exactly
    this)."""
    unit = np.array([[0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], np.float64)
    corners = unit @ homographies.transpose(0, 2, 1)  # (R, 4, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        corner_xy = corners[:, :, :2] / corners[:, :, 2:]
    return (corners[:, :, 2] > 0).all(axis=1) & np.isfinite(corner_xy).all(axis=(1, 2)) \
        & (corner_xy >= 0).all(axis=(1, 2)) & (corner_xy[:, :, 0] <= width - 1).all(axis=1) \
        & (corner_xy[:, :, 1] <= height - 1).all(axis=1)


@cache
def _local_points(size: int, ratio: float) -> np.ndarray:
    """(P, 2) float32 `_sample_grid`'s bit samples, then its ring, as one array (read-only)."""
    bit_points, ring_points = _sample_grid(size, ratio)
    local = np.ascontiguousarray(np.concatenate([bit_points.reshape(-1, 2), ring_points]).astype(np.float32))
    local.flags.writeable = False
    return local


def _square_maps(homographies: np.ndarray, local: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, 3, 3) float32 unit frames -> image, (P, 2) float32 points -> (x (R, P), y (R, P)) float32 pixels:
    (h00 u + h01 v + h02) / (h20 u + h21 v + h22), each product and sum rounded to float32 left to right
    (`decode_kernel.square_maps` computes exactly this)."""
    u, v = local[:, 0], local[:, 1]
    h = homographies[:, :, :, None]  # (R, 3, 3, 1): each entry broadcast over the points
    w = h[:, 2, 0] * u + h[:, 2, 1] * v + h[:, 2, 2]
    x = (h[:, 0, 0] * u + h[:, 0, 1] * v + h[:, 0, 2]) / w
    y = (h[:, 1, 0] * u + h[:, 1, 1] * v + h[:, 1, 2]) / w
    return x, y


def _reduce_reads(values: np.ndarray, grid: int, samples: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R, P) float32 samples (`_local_points`' order) -> (bits (R, grid, grid) float32 each cell's mean sample,
    dark (R,) the median of the border cells, bright (R,) the median of the ring's samples)
    (`decode_kernel.reduce_reads` computes exactly this)."""
    count = len(values)
    sampled = values[:, :grid * grid * samples].reshape(count, grid, grid, samples)
    bits = sampled[..., 0]  # the mean over each bit's samples, summed in np.mean's order
    for k in range(1, samples):
        bits = bits + sampled[..., k]
    bits = bits / np.float32(samples)
    border = np.concatenate([bits[:, 0, :], bits[:, -1, :], bits[:, 1:-1, 0], bits[:, 1:-1, -1]], axis=1)
    return bits, _row_medians(border), _row_medians(values[:, grid * grid * samples:])


def rectify_squares(gray: np.ndarray, homographies: np.ndarray, size: int, ratio: float) -> np.ndarray:
    """(H, W) uint8 image, (R, 3, 3) square unit frames -> image -> (R, P, P) float32 patches on each marker's
    bit grid (`networks.bit_reader.patch_points`: P = (n + 2 + 2 margin) x samples per bit), bilinear, the
    image's border replicated beyond its edges."""
    from deepcharuco.networks.bit_reader import patch_points, patch_side

    side = patch_side(size)
    if len(homographies) == 0:
        return np.zeros((0, side, side), np.float32)
    local = patch_points(size, ratio)
    mapped = homogeneous(local) @ np.asarray(homographies, np.float64).transpose(0, 2, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        points = mapped[:, :, :2] / mapped[:, :, 2:]
    points = np.nan_to_num(points, nan=-1e4, posinf=-1e4, neginf=-1e4).clip(-1e4, 1e5).astype(np.float32)
    return _sample(gray, points.reshape(-1, 2)).reshape(len(homographies), side, side)


@cache
def _bit_reader(path: Path):
    """The learned reader at ``path``, loaded once per process (imported here: "sampled" needs no torch)."""
    from deepcharuco.networks.bit_reader import load_bit_reader

    return load_bit_reader(path)


def learned_bits(gray: np.ndarray, homographies: np.ndarray, size: int, ratio: float,
                 weights: Path = BIT_READER_WEIGHTS, batch: int = 512) -> np.ndarray:
    """(H, W) uint8, (R, 3, 3) square unit frames -> image -> (R, n, n) float32 tanh(logit / `MAX_BIT_LOGIT`) of
    the learned reader's bit logits, in (-1, 1), > 0: white."""
    import torch

    from deepcharuco.networks.bit_reader import normalise_patches

    model = _bit_reader(Path(weights))
    patches = normalise_patches(rectify_squares(gray, homographies, size, ratio))
    out = np.zeros((len(patches), size, size), np.float32)
    with torch.inference_mode():
        for start in range(0, len(patches), batch):
            chunk = torch.from_numpy(patches[start:start + batch])[:, None]
            out[start:start + batch] = model(chunk, size).numpy()
    return np.tanh(out / MAX_BIT_LOGIT)


MAX_REMAP_SIDE = 32767  # cv2.remap's maps take at most this many rows or columns


def _sample(gray: np.ndarray, points: np.ndarray, row: int = 4096) -> np.ndarray:
    """(H, W) image, (P, 2) float32 x, y -> (P,) float32 bilinear samples. ``cv2.remap`` maps take at most
    32767 rows or columns: the points go through as rows of ``row``."""
    count = len(points)
    padded = np.zeros((-(-count // row) * row, 2), np.float32)
    padded[:count] = points
    grid = padded.reshape(-1, row, 2)
    values = cv2.remap(gray, grid[:, :, 0], grid[:, :, 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return values.reshape(-1)[:count].astype(np.float32)


def sample_maps(gray: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(H, W) image, (A, B) float32 x and y -> (A, B) float32 bilinear samples (`_sample`'s values)."""
    if max(x.shape) > MAX_REMAP_SIDE:
        return _sample(gray, np.stack([x.ravel(), y.ravel()], axis=1)).reshape(x.shape)
    return cv2.remap(gray, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float32)


def _normalised(values: np.ndarray) -> np.ndarray:
    """(..., P) -> zero mean, unit norm along the last axis (all-equal rows stay zero). The mean and the norm summed
    as ``np.mean`` and ``np.linalg.norm`` sum them (the same values), without their wrappers' cost on thousands of
    calls."""
    centred = values - np.add.reduce(values, axis=-1, keepdims=True) / values.shape[-1]
    norm = np.sqrt(np.add.reduce(centred * centred, axis=-1, keepdims=True))
    return centred / np.where(norm > 1e-9, norm, 1.0)


def correlate(bits: np.ndarray, markers: BoardMarkers, reader: str | None = None) -> np.ndarray:
    """(R, n, n) reads of ``reader`` (`read_squares`) -> (R, M, 4) scores in [-1, 1] of each board marker in
    each quarter turn: "sampled": NCC of the bit means with the marker's bits; "learned": the cosine of the
    bounded bit logits l with the marker's signs s = 2 b - 1, s . l / (|s| |l|). Within a read it ranks the
    markers as their log-likelihood does (s . l / 2 is it, up to a constant per read); dividing by |l| puts
    a blurred read (all logits small) on the same scale as a sharp one, as NCC's normalisation does, so
    `MIN_NCC` and the placement vote mean the same for both readers."""
    if _reader(reader) == "learned":
        signs = markers.bits.reshape(len(markers.ids) * 4, -1).astype(np.float64) * 2 - 1
        flat = bits.reshape(len(bits), markers.size * markers.size).astype(np.float64)
        norm = np.linalg.norm(flat, axis=1, keepdims=True) * np.sqrt(signs.shape[1])
        return (flat @ signs.T / np.where(norm > 1e-9, norm, 1.0)).reshape(len(bits), len(markers.ids), 4)
    expected = markers.normalised_bits
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
                  per_read: int = PROPOSALS_PER_READ, reader: str | None = None) -> MarkerMatches:
    """(R, n, n) reads of ``reader`` and (R,) contrasts -> each readable read's ``per_read`` best (marker, turn)
    pairs scoring >= `MIN_NCC` (`correlate`), best first within a read, equal scores by the lower (marker, turn)
    (`decode_kernel.best_pairs` chooses the same, compiled)."""
    readable = np.flatnonzero(contrast > 0)
    ncc = correlate(bits[readable], markers, reader).reshape(len(readable), len(markers.ids) * 4)
    if compiled_kernel is not None:
        rows, flat, score = compiled_kernel.best_pairs(np.ascontiguousarray(ncc, np.float64), per_read, MIN_NCC)
        return MarkerMatches(read=readable[rows], marker=flat // 4, turn=flat % 4, ncc=score)
    per_read = min(per_read, ncc.shape[1])
    best = np.argsort(-ncc, axis=1, kind="stable")[:, :per_read]
    rows = np.repeat(np.arange(len(readable)), per_read)
    flat = best.ravel()
    score = ncc[rows, flat] if len(rows) else np.zeros(0)
    keep = score >= MIN_NCC
    return MarkerMatches(read=readable[rows[keep]], marker=flat[keep] // 4, turn=flat[keep] % 4, ncc=score[keep])
