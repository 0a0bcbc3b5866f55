"""Is the board's own pattern around a corner where a view predicts it, even across a cast shadow's edge?

The point head loses corners that a shadow's edge crosses (it learnt X-junctions in one light). Where the
markers have already named such a corner, the image can still say whether the board is there: around the
corner the board's printed pattern is known exactly (two squares, two markers' borders and nearby bits),
so the image near the predicted pixel is compared with it. Light changes that pattern in two ways:

    image = offset + contrast * pattern          (pattern: 1 white paper, 0 ink, in the canonical view)

with one (offset, contrast) on each side of a straight shadow edge anywhere across the window (or no edge).
That holds for the raw image (a shadow scales both) and for an inverted print's negative (`print_face`),
so `pattern_evidence` fits it to the canonical image for every edge in a small set and keeps the best
fit. Where the board shows, the contrast is positive on both sides; an occluder shows no contrast on its
side, and a straight edge through the window (the occluder's outline) is what the model absorbs, not
what it rewards: the pattern is a checker about the corner, which no single straight edge resembles.
The evidence is the smaller of the two sides' t-statistics (contrast / its standard error).
"""

from __future__ import annotations

import dataclasses
from functools import lru_cache

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec, BoardTexture
from deepcharuco.detection.markers.marker_reader import sample_maps

SAMPLES = 16  # samples along each board axis of the window around a corner
HALF_WINDOW = 0.5  # ... which spans this many squares each way: half of each of the four squares at the corner
TEXTURE_PX_PER_SQUARE = 64  # the pattern is sampled from the board drawn this finely
EDGE_ANGLES = 12  # shadow edges tried: this many directions (0-165 degrees) ...
EDGE_OFFSETS = (-0.3, -0.15, 0.0, 0.15, 0.3)  # ... each at these distances from the corner (squares)
# Samples this close to a tried edge (squares) belong to neither side: a penumbra, and the tried edge's miss of the
# true one, would otherwise count against the pattern.
EDGE_GUARD = 0.08
MIN_SIDE = 0.15  # a side of the edge with less of the window than this is not judged
LOCATE_REACH_PX = 1.0  # `locate_by_pattern` tries shifts this far each way ...
LOCATE_STEP_PX = 0.5  # ... this far apart, then a quarter of that around the best


def _window() -> np.ndarray:
    """(S*S, 2) board offsets from a corner, in squares, on a grid of `SAMPLES` a side over +-`HALF_WINDOW`."""
    steps = (np.arange(SAMPLES) + 0.5) / SAMPLES * 2 * HALF_WINDOW - HALF_WINDOW
    x, y = np.meshgrid(steps, steps)
    return np.stack([x.ravel(), y.ravel()], axis=1)


def _edge_lines() -> np.ndarray:
    """(L, 3) the shadow edges tried, as (normal x, normal y, distance) in squares; the first: no edge."""
    lines = [(0.0, 0.0, 1.0)]  # no sample lies beyond distance 1 along a zero normal
    for angle in np.arange(EDGE_ANGLES) * np.pi / EDGE_ANGLES:
        lines.extend((np.cos(angle), np.sin(angle), distance) for distance in EDGE_OFFSETS)
    return np.array(lines)


def _side(across: np.ndarray) -> np.ndarray:
    """Signed distances beyond an edge (squares) -> +1 beyond it, -1 before it, 0 within `EDGE_GUARD` of it."""
    return np.where(across > EDGE_GUARD, 1.0, np.where(across < -EDGE_GUARD, -1.0, 0.0))


WINDOW = _window()
EDGE_LINES = _edge_lines()
EDGE_SIDES = _side(EDGE_LINES[:, :2] @ WINDOW.T - EDGE_LINES[:, 2:])  # (L, S*S)


@lru_cache(maxsize=8)
def printed_pattern(board: BoardSpec) -> BoardTexture:
    """The board as the canonical view shows it (`print_face`: black ink on white, the printed side), drawn once
    per board and kept."""
    face = dataclasses.replace(board, inverted=False, mirrored=False)
    return BoardTexture.render(face, TEXTURE_PX_PER_SQUARE / board.square_length)


def corner_patterns(board: BoardSpec, ids: np.ndarray) -> np.ndarray:
    """(N,) corner IDs -> (N, S*S) the printed pattern (1 paper, 0 ink) at each `WINDOW` sample around them."""
    texture = printed_pattern(board)
    points = board.corner_points()[np.asarray(ids, np.int64), :2]  # (N, 2) metres
    uv = texture.board_to_texture(points[:, None] + WINDOW[None] * board.square_length)  # (N, S*S, 2)
    maps = uv.astype(np.float32).reshape(-1, uv.shape[-2], 2)
    return sample_maps(texture.image, maps[..., 0], maps[..., 1]).reshape(uv.shape[:-1]).astype(np.float64) / 255.0


def window_pixels(homography: np.ndarray, board: BoardSpec, ids: np.ndarray, pixels: np.ndarray,
                  offsets: np.ndarray | None = None) -> np.ndarray:
    """Board offsets around corners ``ids`` (N,) in the image: ``offsets`` (N, M, 2) in squares (default
    `WINDOW` for each), carried by the view ``homography`` (board metres -> pixels) and moved so that each
    corner lands on ``pixels`` (N, 2) (where its neighbours put it: a lens bends the board away from one
    homography). -> (N, M, 2) pixels."""
    points = board.corner_points()[np.asarray(ids, np.int64), :2]
    offsets = np.broadcast_to(WINDOW, (len(points), *WINDOW.shape)) if offsets is None else offsets
    xy = points[:, None] + offsets * board.square_length
    mapped = cv2.perspectiveTransform(xy.reshape(-1, 1, 2).astype(np.float64), homography).reshape(xy.shape)
    centres = cv2.perspectiveTransform(points.reshape(-1, 1, 2).astype(np.float64), homography).reshape(-1, 2)
    return mapped - centres[:, None] + np.asarray(pixels, np.float64)[:, None]


def _sample(gray: np.ndarray, where: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) image, (N, ..., 2) pixels -> (bilinear values (N, ...) float64, (N,) whether all lie in the image)."""
    height, width = gray.shape
    inside = np.all((where >= 0) & (where <= np.array([width - 1, height - 1])), axis=tuple(range(1, where.ndim)))
    maps = where.astype(np.float32).reshape(-1, where.shape[-2], 2)  # a window a row
    return sample_maps(gray, maps[..., 0], maps[..., 1]).reshape(where.shape[:-1]).astype(np.float64), inside


def _moments(values: np.ndarray, pattern: np.ndarray) -> np.ndarray:
    """``values`` and ``pattern`` (..., M), broadcast together -> (..., 6, M): 1, p, p^2, y, p y, y^2 at each sample,
    whose sums over one side of an edge are all that side's regression needs."""
    values, pattern = np.broadcast_arrays(values, pattern)
    return np.stack([np.ones_like(values), pattern, pattern * pattern, values, pattern * values, values * values], -2)


def _side_masks(side: np.ndarray) -> np.ndarray:
    """(..., M) sides (-1, +1; 0 leaves a sample out) -> (..., 2, M) float64: the samples of side -1, then of +1."""
    return np.stack([side < 0, side > 0], -2).astype(np.float64)


EDGE_MASKS = _side_masks(EDGE_SIDES)  # (L, 2, S*S)


def _fit(sums: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least squares of the values on an offset + contrast * pattern of their own on each side of an edge: one
    straight-line regression per side, in closed form, from ``sums`` (..., 2, 6): each side's sums of `_moments`.
    -> (residual variance (...): the residual sum of squares over the samples used less 4; the two sides'
    contrasts (..., 2); 1 / each side's pattern's sum of squared deviations (..., 2): a contrast's variance is
    this times the residual variance; inf for a side without pattern variation, whose contrast is 0)."""
    n, sp, spp, sy, spy, syy = np.moveaxis(sums, -1, 0)  # each (..., 2)
    count = np.maximum(n, 1.0)
    sxx, sxy, syy_centred = spp - sp * sp / count, spy - sp * sy / count, syy - sy * sy / count
    varied = sxx > 1e-9 * count
    contrast = np.where(varied, sxy / np.where(varied, sxx, 1.0), 0.0)
    rss = np.maximum(syy_centred - contrast * sxy, 0.0).sum(-1)
    variance = rss / np.maximum(n.sum(-1) - 4.0, 1.0)
    return variance, contrast, np.where(varied, 1.0 / np.where(varied, sxx, 1.0), np.inf)


def _fit_every_edge(values: np.ndarray, pattern: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`_fit` of windows ``values`` (N, M) on their ``pattern`` (N, M) for every edge in `EDGE_SIDES` -> (N, L),
    (N, L, 2), (N, L, 2). The edges' sides are the same for every window: one matrix product sums them all."""
    sums = np.tensordot(_moments(values, pattern), EDGE_MASKS, axes=([2], [2]))  # (N, 6, L, 2)
    return _fit(np.transpose(sums, (0, 2, 3, 1)))


def pattern_evidence(gray: np.ndarray, board: BoardSpec, homography: np.ndarray, ids: np.ndarray,
                     pixels: np.ndarray) -> np.ndarray:
    """How surely the board's printed pattern lies around each predicted corner, a shadow's edge allowed.

    Args:
        gray: (H, W) uint8 image in the board's canonical appearance (`print_face.canonical_view`).
        board: the board; homography: (3, 3) its view, board metres -> ``gray``'s pixels.
        ids: (N,) corner IDs; pixels: (N, 2) where each is predicted in ``gray``.

    Returns:
        (N,) float64: the smaller t-statistic of the pattern's contrast on the two sides of the best-fitting
        shadow edge (`EDGE_SIDES`; a side with less than `MIN_SIDE` of the window is not judged); -inf for a
        window that leaves the image.
    """
    ids = np.asarray(ids, np.int64)
    if len(ids) == 0:
        return np.zeros(0)
    values, inside = _sample(gray, window_pixels(homography, board, ids, pixels))  # (N, S2)
    pattern = corner_patterns(board, ids)
    variance, contrast, spread = _fit_every_edge(values, pattern)  # (N, L), (N, L, 2) x2
    best = np.argmin(variance, axis=1)  # (N,) the edge that explains the window best
    rows = np.arange(len(ids))
    spread, variance = spread[rows, best], variance[rows, best, None]
    # A side without pattern variation has infinite spread: no evidence (t = 0), also where nothing varies at all.
    with np.errstate(invalid="ignore"):  # inf * 0 where nothing varies: taken as inf by the where
        error = np.where(np.isinf(spread), np.inf, np.sqrt(np.maximum(spread * variance, 1e-12)))
    t = contrast[rows, best] / error  # (N, 2): side -1, side +1
    share = EDGE_MASKS[best].mean(axis=2)  # (N, 2): each side's fraction of the window
    evidence = np.where(share >= MIN_SIDE, t, np.inf).min(axis=1)
    return np.where(inside, evidence, -np.inf)


def locate_by_pattern(gray: np.ndarray, board: BoardSpec, homography: np.ndarray, ids: np.ndarray,
                      pixels: np.ndarray, reach_px: float = LOCATE_REACH_PX) -> np.ndarray:
    """Corners placed where the board's printed pattern fits the image best, a shadow's edge allowed: the shadow
    edge that fits best at ``pixels`` (N, 2) stays where it is in the image while the pattern's window moves over
    shifts up to ``reach_px`` (a grid of `LOCATE_STEP_PX`, then one of a quarter of it around the best; a parabola
    through the best and its neighbours on each axis gives the last fraction). RefineNet, which learnt corners in
    one light, is pulled towards a shadow's edge; the pattern is not.

    ``gray``, ``board``, ``homography``, ``ids`` as in `pattern_evidence`. -> (N, 2) float64 pixels."""
    ids = np.asarray(ids, np.int64)
    pixels = np.asarray(pixels, np.float64).reshape(-1, 2)
    if len(ids) == 0:
        return pixels
    window = window_pixels(homography, board, ids, pixels)  # (N, S2, 2)
    values, _ = _sample(gray, window)
    pattern = corner_patterns(board, ids)  # (N, S2)
    variance = _fit_every_edge(values, pattern)[0]
    lines = EDGE_LINES[np.argmin(variance, axis=1)]  # (N, 3) in squares about the starting pixel
    # Over a shift of a pixel or two the window moves as a whole (its perspective changes by far less than a
    # sample); the edge stays put in the image, so each sample's side moves by the shift, in squares.
    across = lines[:, :2] @ WINDOW.T - lines[:, 2:]  # (N, S2)
    axes = window_pixels(homography, board, ids, pixels, np.broadcast_to(np.array([[1.0, 0.0], [0.0, 1.0]]),
                                                                          (len(ids), 2, 2))) - pixels[:, None]
    to_squares = np.linalg.inv(np.transpose(axes, (0, 2, 1)))  # (N, 2, 2): pixels -> squares
    shift = np.zeros((len(ids), 2))
    rows = np.arange(len(ids))
    for step, count in ((LOCATE_STEP_PX, int(round(reach_px / LOCATE_STEP_PX))), (LOCATE_STEP_PX / 4, 2)):
        grid = np.arange(-count, count + 1) * step
        moves = shift[:, None] + np.stack(np.meshgrid(grid, grid), axis=-1).reshape(1, -1, 2)  # (N, G, 2) px
        moved_across = np.einsum("nij,ngj,ni->ng", to_squares, moves, lines[:, :2])  # (N, G) squares along the normal
        values, _ = _sample(gray, window[:, None] + moves[:, :, None])  # (N, G, S2)
        sides = _side_masks(_side(across[:, None] + moved_across[:, :, None]))  # (N, G, 2, S2)
        variance = _fit(sides @ np.swapaxes(_moments(values, pattern[:, None]), -1, -2))[0]  # (N, G)
        side_count = len(grid)
        best = np.argmin(variance, axis=1)
        row, column = np.divmod(best, side_count)
        surface = variance.reshape(-1, side_count, side_count)
        fraction = np.stack([_vertex(surface[rows, row], column), _vertex(surface[rows, :, column], row)], axis=1)
        shift = moves[rows, best] + (fraction * step if step < LOCATE_STEP_PX else 0.0)
    return pixels + shift


def _vertex(curve: np.ndarray, at: np.ndarray) -> np.ndarray:
    """(N, G) values along a line of shifts, (N,) the index of each minimum -> (N,) the offset (in grid steps, within
    +-0.5) of the parabola through it and its two neighbours; 0 at the line's ends or where it does not open up."""
    rows = np.arange(len(curve))
    inner = (at > 0) & (at < curve.shape[1] - 1)
    left = curve[rows, np.clip(at - 1, 0, None)]
    middle = curve[rows, at]
    right = curve[rows, np.clip(at + 1, None, curve.shape[1] - 1)]
    bend = left - 2 * middle + right
    offset = np.where(inner & (bend > 0), 0.5 * (left - right) / np.where(bend > 0, bend, 1.0), 0.0)
    return np.clip(offset, -0.5, 0.5)
