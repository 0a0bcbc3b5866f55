"""Where a finer search level looks: the regions of a frame a coarser level saw a board, or board-like cells in.

A board whose squares are a little too small for a level (7-12 px there) is still seen by its point head as a
dense patch of corner-like cells: a 5x5-cell window over it holds 12-15 cells of confidence >= 0.3, where
procedural clutter, text and tiled grids hold at most 1 (the paper's board drawn at 1280x720, searched at 320
px; real rooms hold more). The next level, with squares twice as wide, then searches those patches alone, not
the whole frame: a frame without a board stops at the levels searched whole, and a small board costs the pixels
around it.

Boxes are (x0, y0, x1, y1) with exclusive ends, in the pixels of the image they are given for.
"""

from __future__ import annotations

import cv2
import numpy as np

from deepcharuco.networks.cells import CELL

# A finer level searches where the level before saw MIN_CELLS corner-like cells (point confidence >= CONFIDENCE, the
# decoding's own threshold) in a WINDOW_CELLS-square window; the inverted print's second, local-white search runs only
# where the first saw such a patch. Chosen on validation frames (`benchmarks/detect.py`'s frames at seed 1, the
# caliscope videos, calibtargets' photos): every frame found what searching every level whole found; 0.1 and 4 cells
# found the same at 2.3x the time on the caliscope webcams, whose rooms show such texture everywhere.
CONFIDENCE = 0.3
MIN_CELLS = 6
# In a dim frame (the coarse level's 99th percentile grey below DIM_WHITE: darkness k >= 3 of the paper's protocol;
# lit webcam frames read 190-252) the point head is less sure everywhere, and a patch counts from DIM_MIN_CELLS cells
# of confidence >= DIM_CONFIDENCE: on caliscope_extra's video at darkness k = 7 the stricter patch lost 3 of the 141
# frames found by searching every level whole; this finds all 141.
DIM_WHITE = 64
DIM_CONFIDENCE = 0.1
DIM_MIN_CELLS = 4
WINDOW_CELLS = 5  # the window corner-like cells are counted in
MARGIN_CELLS = 3  # board-like cells widened by this many cells: the markers and corners beyond them
MIN_SIDE_CELLS = 8  # a region narrower than this many cells is widened to it (the network needs context)

Box = tuple[int, int, int, int]


def is_dim(gray: np.ndarray) -> bool:
    """Whether a (H, W) uint8 image is dim: its 99th percentile grey (`white_level`) below `DIM_WHITE`."""
    return white_level(gray) < DIM_WHITE


def white_level(gray: np.ndarray) -> int:
    """A (H, W) uint8 image's 99th percentile grey, its value of rank 0.99 (N - 1) in sorted order: how bright its
    white is, whatever lamps light 1 % of it (counted from one histogram, not sorted)."""
    histogram = cv2.calcHist([gray], [0], None, [256], [0, 256]).ravel()
    return int(np.searchsorted(np.cumsum(histogram), int(0.99 * (gray.size - 1)) + 1))


def corner_cells(confidence: np.ndarray) -> int:
    """How many cells of (Hc, Wc) point confidences are corner-like: confidence >= `CONFIDENCE`."""
    return int(np.count_nonzero(confidence >= CONFIDENCE))


def board_like_boxes(confidence: np.ndarray, dim: bool = False, board_corners: int | None = None) -> list[Box]:
    """(Hc, Wc) cell confidences of one level -> boxes, in that level's cells, around each dense patch of
    corner-like cells (`MIN_CELLS` or more of confidence >= `CONFIDENCE` in a `WINDOW_CELLS` square window;
    in a ``dim`` frame `DIM_MIN_CELLS` of `DIM_CONFIDENCE`), widened by `MARGIN_CELLS`; [] where the level saw
    none. A board of fewer corners than `MIN_CELLS` (``board_corners``: a 3x3 board has 4) makes a patch from all
    of them at `DIM_CONFIDENCE`: its few corners give no dense patch, and at a level where its squares are ~17 px
    one of the four read 0.11 (validation: 8 frames drawn as `benchmarks/detect.py`'s 5 MP row draws them, rng
    seed 0)."""
    min_confidence, min_cells = (DIM_CONFIDENCE, DIM_MIN_CELLS) if dim else (CONFIDENCE, MIN_CELLS)
    if board_corners is not None and board_corners < MIN_CELLS:
        min_confidence, min_cells = DIM_CONFIDENCE, min(DIM_MIN_CELLS, board_corners)
    hot = (confidence >= min_confidence).astype(np.float32)
    counts = cv2.boxFilter(hot, -1, (WINDOW_CELLS, WINDOW_CELLS), normalize=False, borderType=cv2.BORDER_CONSTANT)
    dense = ((counts >= min_cells) & (hot > 0)).astype(np.uint8)
    if not dense.any():
        return []
    side = 2 * MARGIN_CELLS + 1
    grown = cv2.dilate(dense, np.ones((side, side), np.uint8))
    count, _, stats, _ = cv2.connectedComponentsWithStats(grown, connectivity=8)
    return [(int(x), int(y), int(x + w), int(y + h)) for x, y, w, h, _ in stats[1:count]]


def to_full(boxes: list[Box], scale: float, image_size: tuple[int, int], min_side: int = MIN_SIDE_CELLS * CELL
            ) -> list[Box]:
    """``boxes`` in a level's cells, that level ``scale`` times the full image -> boxes in the full image's
    pixels (``image_size`` (W, H)), each at least ``min_side`` level pixels wide and high, inside the image."""
    width, height = image_size
    full = []
    for x0, y0, x1, y1 in boxes:
        low = np.array([x0, y0], np.float64) * CELL / scale
        high = np.array([x1, y1], np.float64) * CELL / scale
        grow = np.maximum(min_side / scale - (high - low), 0) / 2
        low, high = np.floor(low - grow), np.ceil(high + grow)
        low = np.clip(low, 0, None)
        high = np.minimum(high, [width, height])
        full.append((int(low[0]), int(low[1]), int(high[0]), int(high[1])))
    return full


def area_share(boxes: list[Box], image_size: tuple[int, int]) -> float:
    """The share of a (W, H) image the ``boxes`` cover, overlaps counted twice (an upper bound, which is all the
    choice between regions and the whole image needs)."""
    width, height = image_size
    return min(1.0, sum((x1 - x0) * (y1 - y0) for x0, y0, x1, y1 in boxes) / (width * height))
