"""The deep detector's search levels and what passes between them: the network's input (`network_input`), a
frame reduced to a level (`reduced`) and a region of it mapped back (`on_cell_grid`, `to_level`), the candidates
inside the image (`candidates_in_image`), RefineNet's patches (`patches_around`) and its early start on a second
thread (`EarlyRefinement`), a preview corner nudged onto the corner (`nudged`, `moves_limited`), and a level's
result (`Found`) and what a search saw besides it (`Seen`). Pixels OpenCV's (centre of the top-left pixel at (0, 0)).
"""

from __future__ import annotations

from concurrent.futures import Future
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

from deepcharuco.core.vectors import lengths
from deepcharuco.detection.search_regions import Box, white_level
from deepcharuco.networks.cells import CELL, CellCandidates
from deepcharuco.networks.offsets import PATCH
from deepcharuco.networks.shipped import DEFAULT_WEIGHTS, FAMILY_WEIGHTS_DIR, WEIGHTS_DIR  # noqa: F401 (WEIGHTS_DIR: API)


PATCH_ORIGIN = 12  # a candidate pixel sits at patch pixel 12, inside the central 8x8 (8..15)


# A preview's corners are centred by cornerSubPix (5x5 window there, 10x10 at full size), at most 1.5 px,
# before RefineNet refines them at full resolution: one RefineNet pass instead of two. Chosen on validation
# (renders seed 2000, all protocol levels within 0.002 of two RefineNet passes, 213 vs 233 wrong corners;
# sequences seed 2001, good light: corner error 0.074 vs 0.075 px, eps_re 0.058 vs 0.060). A 7x7 window or
# a 1.0 / 2.5 px limit did no better.
PREVIEW_SUBPIX_HALF_WINDOW = 2
PREVIEW_MAX_NUDGE_PX = 1.5


def network_input(gray: np.ndarray, white: float | None = None) -> np.ndarray:
    """(H, W) uint8 -> ChArUcoNet's input (1, 1, H', W') float32 in [0, 1]: the network sees whole 8x8 cells,
    so the image is padded right and bottom to multiples of 8 by replicating its border. ``white`` (a network's
    bundle's ``input_white``): an image whose 99th percentile grey is below ``white`` (in [0, 1]) is scaled so that it
    reaches it (`brightness_gain`), clipped at 1."""
    height, width = gray.shape
    padded = cv2.copyMakeBorder(gray, 0, -height % CELL, 0, -width % CELL, cv2.BORDER_REPLICATE)
    gain = brightness_gain(gray, white)
    if gain == 1.0:
        return padded[None, None] / np.float32(255.0)
    return np.minimum(padded[None, None] * np.float32(gain / 255.0), np.float32(1.0))


def brightness_gain(gray: np.ndarray, white: float | None) -> float:
    """The factor that brings the (H, W) uint8 image's 99th percentile grey (`search_regions.white_level`, at least 1)
    up to ``white`` * 255, or 1 where it is there already or ``white`` is None."""
    if white is None:
        return 1.0
    return max(1.0, white * 255.0 / max(white_level(gray), 1))


def reduced(image: np.ndarray, scale: float) -> np.ndarray:
    """``image`` scaled by ``scale`` < 1 (area-averaged, as a sensor's larger pixels would see it)."""
    height, width = image.shape
    return cv2.resize(image, (max(1, round(width * scale)), max(1, round(height * scale))), interpolation=cv2.INTER_AREA)


def nudged(gray: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(N, 2) corner pixels -> (N, 2) float32 moved by cornerSubPix (window `PREVIEW_SUBPIX_HALF_WINDOW`),
    each by at most `PREVIEW_MAX_NUDGE_PX`: a corner it would move farther keeps its pixel."""
    window = (PREVIEW_SUBPIX_HALF_WINDOW, PREVIEW_SUBPIX_HALF_WINDOW)
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 0.01)
    nudged = cv2.cornerSubPix(gray, pixels.reshape(-1, 1, 2).astype(np.float32), window, (-1, -1), criteria).reshape(-1, 2)
    return moves_limited(nudged, pixels, PREVIEW_MAX_NUDGE_PX)


def moves_limited(refined: np.ndarray, pixels: np.ndarray, max_move: float) -> np.ndarray:
    """(N, 2) ``refined`` corners, each one moved farther than ``max_move`` px from its ``pixels`` row put back there."""
    far = lengths(refined - pixels) > max_move
    refined[far] = pixels[far]
    return refined


def patches_around(gray: np.ndarray, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) integer corner pixels -> (their patches' top-left pixels (N, 2) int64, (N, 1, 24, 24) float32
    patches in [0, 1] whose pixel 12 is each corner pixel; the image's border replicated beyond its edges)."""
    border = PATCH
    padded = cv2.copyMakeBorder(gray, border, border, border, border, cv2.BORDER_REPLICATE)
    origins = pixels.astype(np.int64) - PATCH_ORIGIN
    windows = np.lib.stride_tricks.sliding_window_view(padded, (PATCH, PATCH))  # a view: (H', W', 24, 24)
    patches = windows[origins[:, 1] + border, origins[:, 0] + border]
    return origins, patches[:, None] / np.float32(255.0)


@dataclass(frozen=True)
class EarlyRefinement:
    """RefineNet run on a second thread for the confident candidates of one search level while its markers are
    read (the decoding is numpy on one core, the other idle): ``gray`` the level's image, ``pixels`` (N, 2)
    integer candidate pixels, ``origins`` (N, 2) their patches' top-left pixels, ``logits`` the future of
    RefineNet's (N, 4096) logits."""

    gray: np.ndarray
    pixels: np.ndarray
    origins: np.ndarray
    logits: Future

    def lookup(self, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(M, 2) pixels -> ((M,) bool whether each was refined here, (K,) its rows in ``self.pixels``)."""
        width = self.gray.shape[1] + 2 * PATCH  # keys stay distinct for pixels a little outside the image too
        keys = self.pixels[:, 1].astype(np.int64) * width + self.pixels[:, 0].astype(np.int64)
        wanted = pixels[:, 1].astype(np.int64) * width + pixels[:, 0].astype(np.int64)
        order = np.argsort(keys, kind="stable")
        at = np.clip(np.searchsorted(keys[order], wanted), 0, len(keys) - 1)
        done = (keys[order][at] == wanted) & (pixels == np.rint(pixels)).all(axis=1)
        return done, order[at[done]]


def on_cell_grid(box: Box, scale: float, image_size: tuple[int, int]) -> Box:
    """``box`` (full pixels) widened onto the cell grid of the level ``scale`` times the full image (W, H)
    ``image_size``: its region, reduced, is then the same pixels and the same cells the network sees in the whole
    level (where 8 / ``scale`` is a whole number of pixels), so a region finds what the whole level would there."""
    step = CELL / scale
    width, height = image_size
    x0, y0, x1, y1 = box
    return (int(np.floor(x0 / step) * step), int(np.floor(y0 / step) * step),
            min(int(np.ceil(np.ceil(x1 / step) * step)), width), min(int(np.ceil(np.ceil(y1 / step) * step)), height))


@dataclass(frozen=True)
class Found:
    """What one search level found: ``box`` (x0, y0, x1, y1) the region of the canonical image it searched (full
    pixels, exclusive ends), ``region`` that part of the image, ``gray`` the same at the level's scale (``region``
    itself at full scale), (ids (N,), integer pixels (N, 2) in ``gray``, scores (N,)), whether it is the
    half-size ``preview``, its `EarlyRefinement` or None, and the view its markers verified (3x3, board metres ->
    ``gray``'s pixels; None where the corners were not found by their markers)."""

    box: Box
    region: np.ndarray
    gray: np.ndarray
    ids: np.ndarray
    pixels: np.ndarray
    scores: np.ndarray
    preview: bool
    early: EarlyRefinement | None
    view: np.ndarray | None = None

    def ratio(self) -> np.ndarray:
        """(2,) float32 full-resolution pixels per ``gray`` pixel, in x and y."""
        return np.array([self.region.shape[1] / self.gray.shape[1], self.region.shape[0] / self.gray.shape[0]],
                        np.float32)


class Seen(NamedTuple):
    """What a search saw besides what it found: ``board_like``, whether a level saw board-like cells
    (`search_regions.board_like_boxes`) or a board; ``dim``, whether the first level it searched whole was dim
    (`search_regions.is_dim`); ``corner_cells``, the most cells of point confidence >= `search_regions.CONFIDENCE`
    one pass of the network showed (a level searched whole, a region of one, or the preview)."""

    board_like: bool = False
    dim: bool = False
    corner_cells: int = 0

    def merged(self, other: Seen) -> Seen:
        """Both searches' cues: board-like where either saw it, ``other``'s dimness (the later search's first
        level), the more corner-like cells."""
        return Seen(self.board_like or other.board_like, other.dim, max(self.corner_cells, other.corner_cells))


def level_map(box: Box, level_shape: tuple[int, int], region_shape: tuple[int, int]) -> np.ndarray:
    """3x3 map from a full image's pixels to those of the search level that reduced the full image's ``box`` (its
    (H, W) ``region_shape``) to ``level_shape`` (pixel centres to centres)."""
    rx, ry = level_shape[1] / region_shape[1], level_shape[0] / region_shape[0]
    x0, y0 = box[:2]
    return np.array([[rx, 0.0, 0.5 * rx - 0.5 - rx * x0], [0.0, ry, 0.5 * ry - 0.5 - ry * y0], [0.0, 0.0, 1.0]])


def to_level(view: np.ndarray | None, box: Box, level_shape: tuple[int, int], region_shape: tuple[int, int]
             ) -> np.ndarray | None:
    """``view`` (3x3, board -> a full image's pixels) -> board -> the search level's pixels (`level_map`); None stays
    None."""
    return None if view is None else level_map(box, level_shape, region_shape) @ view


def from_level(view: np.ndarray, box: Box, level_shape: tuple[int, int], region_shape: tuple[int, int]) -> np.ndarray:
    """``view`` (3x3, board -> a search level's pixels) -> board -> the full image's pixels (`level_map` inverted)."""
    return np.linalg.inv(level_map(box, level_shape, region_shape)) @ view


def candidates_in_image(candidates: CellCandidates, image_size: tuple[int, int]) -> CellCandidates:
    """The candidates inside the (width, height) image, not in the padding the network saw."""
    width, height = image_size
    return candidates.subset((candidates.pixels[:, 0] < width) & (candidates.pixels[:, 1] < height))
