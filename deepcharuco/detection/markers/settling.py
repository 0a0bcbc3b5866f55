"""Corners settled against their neighbours once the board is placed: a corner far from where its neighbours'
local fit puts it is moved there or dropped (`settle_corners`, `local_predictions`), every corner's distance from
that prediction becomes its sigma floor (`neighbour_distances`), and corners with too few neighbours are dropped
(`drop_isolated`). Pixels OpenCV's.
"""

from __future__ import annotations


import numpy as np

from deepcharuco.core.vectors import lengths


LOCAL_SQUARES = 2  # a weak candidate is sought where the found corners within this many squares put its corner


# After refinement a filled-in corner must lie within FILL_IN_AGREE_PX, or FILL_IN_NOISE times its refined confident
# neighbours' own scatter about their local homography, of where they put it (`settle_corners`). Validation renders
# (10x7 DICT_5X5_1000, 5x4 DICT_4X4_250 inverted, 12x9 DICT_4X4_1000; seed 1313): in good light and at k = 0 every right
# fill-in lay within 0.50 px of that prediction (845 of them; the neighbours' scatter 0.07 px), the one beyond 1 px was
# 3.5 px off the truth; at darkness k = 9 the neighbours scatter 1.2 px and 55 of 71 fill-ins lie beyond 1 px (52 of
# them within the 3 px rule, 1-3 px off): 3x the scatter keeps all but 13 there. 1.0 px is twice the good-light maximum.
FILL_IN_AGREE_PX = 1.0
FILL_IN_NOISE = 3.0


# A confident corner must lie within OUTLYING_PX, or OUTLYING_NOISE times the scatter, of where at least
# OUTLYING_MIN_NEIGHBOURS confident neighbours around it put it (`settle_corners`). Validation (every second frame of
# the rendered sequences of the three boards above, 8x6 DICT_6X6_1000 and 4x6 DICT_4X4_250 inverted, and blur and
# darkness applied to 20 well-lit frames of each; 2,788 detections, not the report's boards): it leaves out 31 right
# corners in well-lit sequences, each 2.1-2.8 px off its truth (glare), 24 at blur k = 10 (1.4-2.6 px off; accuracy
# 0.969 -> 0.964), 0-4 in each other condition (1.1-2.6 px off), and 3 wrong ones; good-light eps_re 0.0842 -> 0.0834
# px, pose accuracy 100 % before and after. 1 px (the fill-ins' limit) left out nearly twice as many right corners
# under blur for no better pose. With no neighbour on either side of it along a board axis (most edge corners), or
# neighbours all on one line, the fit extrapolates, up to 30 px off good corners: those go unchecked.
OUTLYING_PX = 1.5
OUTLYING_NOISE = 5.0
OUTLYING_MIN_NEIGHBOURS = 6
RIDGE = 1e-9  # added to the local fits' normal equations (entries ~1-100): solvable always, the same fits


# A corner with fewer than MIN_NEIGHBOURS other found corners within LOCAL_SQUARES squares of it on the board, in a
# detection of at least ISOLATION_MIN_CORNERS, is left out (`drop_isolated`): its ID rests on the view's one homography
# carried far from the corners it was fitted on, and a wide lens bends a big board's edge a whole square from it.
# Validation renders of random DICT_4X4/5X5/6X6 boards (seed 9137 at 320x240; seeds 4242/4243 at 720x540; not the
# report's boards), frames with a corner 6 px or more off its truth (mostly IDs a square off), before -> after:
# the paper's weights 16 -> 13 frames, 80 of 12,746 right corners left out (0.6 %); the DICT_4X4 family model 16 -> 9,
# 53 of 12,902 (0.4 %); no frame lost its >= 4 right corners. Fewer than 4 neighbours: 10 and 6 frames for 242 and 214
# right corners. Below 10 corners (darkness, a small board) most corners have few neighbours found: left as found.
MIN_NEIGHBOURS = 3
ISOLATION_MIN_CORNERS = 10


def settle_corners(board_xy: np.ndarray, ids: np.ndarray, corners: np.ndarray, scores: np.ndarray,
                   threshold: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """After refinement every corner must lie where the refined confident corners (score >= ``threshold``) within
    `LOCAL_SQUARES` squares of it put it (`local_predictions`, a homography fitted to them), up to a limit that
    grows with their own scatter about the fit; in the dark every corner scatters, and the limit with it.

    - A filled-in corner (score below ``threshold``, `_fill_in`) stays only within `FILL_IN_AGREE_PX`, or
      `FILL_IN_NOISE` times the scatter, of where at least 4 of them put it: a weak candidate can be a corner
      washed out by glare or a shadow edge, which RefineNet then places a pixel or two off.
    - A confident corner goes when it lies beyond `OUTLYING_PX`, or `OUTLYING_NOISE` times the scatter, from where
      the others put it; checked only where at least `OUTLYING_MIN_NEIGHBOURS` of them span both board axes and lie
      on both sides of it along one (elsewhere the prediction extrapolates). The point head can be sure of a corner
      that glare or a shadow edge has moved, and RefineNet then centres it on the glare's edge.

    Either is right by the 3 px rule and wrong for a pose or a calibration.
    ``board_xy``: (C, 2) the board's corners; ``ids`` (N,), ``corners`` (N, 2), ``scores`` (N,) a detection.
    Returns (ids, corners, scores) without the corners that disagree, order kept."""
    strong = np.flatnonzero(scores >= threshold)
    offsets, weight, slots = _neighbourhoods(board_xy, ids, ids[strong])
    weak = scores < threshold
    fittable = _fittable(offsets, weight)
    surrounded = fittable & (weight.sum(axis=1) >= OUTLYING_MIN_NEIGHBOURS) & _both_sides(offsets, weight)
    checked = np.where(weak, fittable, surrounded)
    keep = ~weak  # a fill-in without 4 confident neighbours to check it against goes
    if checked.any():
        predicted, misfit = local_predictions(offsets[checked], weight[checked],
                                              corners[strong].astype(np.float64)[slots[checked]])
        scatter = _scatter(misfit, weight[checked])
        limit = np.where(weak[checked], np.maximum(FILL_IN_AGREE_PX, FILL_IN_NOISE * scatter),
                         np.maximum(OUTLYING_PX, OUTLYING_NOISE * scatter))
        keep[checked] = lengths(predicted - corners[checked]) <= limit
    return ids[keep], corners[keep], scores[keep]


def neighbour_distances(board_xy: np.ndarray, ids: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """(N,) px: how far each of a detection's (N, 2) ``corners`` (IDs ``ids`` (N,); ``board_xy`` (C, 2) the board's
    corners) lies from where the others within `LOCAL_SQUARES` squares of it put it (`local_predictions`); NaN where
    they are fewer than 4 or on one line."""
    offsets, weight, slots = _neighbourhoods(board_xy, ids, ids)
    distance = np.full(len(ids), np.nan)
    fittable = _fittable(offsets, weight)
    if fittable.any():
        predicted, _ = local_predictions(offsets[fittable], weight[fittable],
                                         np.asarray(corners, np.float64)[slots[fittable]])
        distance[fittable] = lengths(predicted - corners[fittable])
    return distance


def _neighbourhoods(board_xy: np.ndarray, targets: np.ndarray, ids: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each target corner's neighbours among ``ids`` ((N,) corner IDs): the others within `LOCAL_SQUARES` squares
    of it on the board, gathered into K slots per target (K their most in any target) -> (offsets (T, K, 2) their
    board places relative to the target in squares, weight (T, K) 1 for a neighbour and 0 for an empty slot,
    slots (T, K) their indices into ``ids``). ``board_xy``: (C, 2) the board's corners; ``targets``: (T,) IDs."""
    offsets = _board_offsets(board_xy, targets, ids)
    near = _near(offsets)
    width = int(near.sum(axis=1).max()) if near.size else 0
    slots = np.argsort(~near, axis=1, kind="stable")[:, :width]
    weight = np.take_along_axis(near, slots, axis=1).astype(np.float64)
    return np.take_along_axis(offsets, slots[..., None], axis=1), weight, slots


def _board_offsets(board_xy: np.ndarray, targets: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """(T, N, 2) the board places of corners ``ids`` (N,) relative to each of ``targets`` (T,), in squares."""
    grid = np.rint(board_xy / float(np.linalg.norm(board_xy[1] - board_xy[0])))
    return grid[ids][None] - grid[targets][:, None]


def _near(offsets: np.ndarray) -> np.ndarray:
    """(T, N) bool from `_board_offsets`: other corners within `LOCAL_SQUARES` squares along both board axes."""
    reach = np.maximum(np.abs(offsets[..., 0]), np.abs(offsets[..., 1]))
    return (reach <= LOCAL_SQUARES) & (reach > 0)


def _fittable(offsets: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """(T,) bool: targets with at least 4 neighbours (`_neighbourhoods`' ``offsets`` (T, K, 2) and ``weight``
    (T, K)), not all on one line: a homography fits them and says where the target is."""
    x, y = offsets[..., 0], offsets[..., 1]
    count = weight.sum(axis=1)
    safe = np.maximum(count, 1)
    dx = (x - ((weight * x).sum(axis=1) / safe)[:, None]) * weight
    dy = (y - ((weight * y).sum(axis=1) / safe)[:, None]) * weight
    spread = (dx * dx).sum(axis=1) * (dy * dy).sum(axis=1) - (dx * dy).sum(axis=1) ** 2  # 0 on one line
    return (count >= 4) & (spread > 1e-6)


def _both_sides(offsets: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """(T,) bool: targets with neighbours on both sides of them along at least one board axis (a prediction there
    interpolates along that axis)."""
    present = weight > 0
    sides = [((axis < 0) & present).any(axis=1) & ((axis > 0) & present).any(axis=1)
             for axis in (offsets[..., 0], offsets[..., 1])]
    return sides[0] | sides[1]


def _scatter(misfit: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """(T,) the neighbours' RMS distance from their fit (`local_predictions`' ``misfit`` (T, K)), its 8 degrees of
    freedom taken: 0 for 4 neighbours, which any homography fits."""
    count = weight.sum(axis=1)
    return np.sqrt((misfit ** 2).sum(axis=1) / np.maximum(2 * count - 8, 1))


def local_predictions(offsets: np.ndarray, weight: np.ndarray, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where each target corner's neighbours put it, all targets at once: per target the homography from board
    places to pixels that fits its neighbours best (least squares, direct linear transform with the pixels
    normalised), evaluated at the target. A lens bends the board away from any one homography; a few squares of
    it stay nearly flat.

    Args:
        offsets: (T, K, 2) the neighbours' board places relative to the target, in squares (`_neighbourhoods`).
        weight: (T, K) 1 for a neighbour, 0 for an empty slot; each target has at least 4 neighbours, not all on
            one line (`_fittable`).
        image: (T, K, 2) float64 the neighbours' pixels.

    Returns:
        predicted (T, 2) pixels and misfit (T, K): each neighbour's distance in pixels from where the fit puts it
        (0 in empty slots).
    """
    count = weight.sum(axis=1)
    centre = (weight[..., None] * image).sum(axis=1) / count[:, None]
    image = image - centre[:, None]
    scale = np.sqrt((weight * (image ** 2).sum(axis=2)).sum(axis=1) / count)  # well-conditioned normal equations
    u, v = image[..., 0] / scale[:, None], image[..., 1] / scale[:, None]
    x, y = offsets[..., 0], offsets[..., 1]
    zero, one = np.zeros_like(x), np.ones_like(x)
    rows = np.concatenate([np.stack([x, y, one, zero, zero, zero, -u * x, -u * y], axis=2),
                           np.stack([zero, zero, zero, x, y, one, -v * x, -v * y], axis=2)], axis=1)
    rows *= np.concatenate([weight, weight], axis=1)[..., None]
    rhs = np.concatenate([u * weight, v * weight], axis=1)[..., None]
    transposed = rows.transpose(0, 2, 1)
    # A tiny ridge keeps the system solvable where the neighbours' pixels all lie on one line (a board seen edge-on,
    # which no verified view is): np.linalg.solve would raise on the whole batch.
    normal = transposed @ rows + RIDGE * np.eye(8)
    h = np.linalg.solve(normal, transposed @ rhs)[..., 0]  # (T, 8), h33 = 1: the target is no horizon point
    with np.errstate(divide="ignore", invalid="ignore"):
        w = h[:, None, 6] * x + h[:, None, 7] * y + 1.0
        misfit_u = (h[:, None, 0] * x + h[:, None, 1] * y + h[:, None, 2]) / w - u
        misfit_v = (h[:, None, 3] * x + h[:, None, 4] * y + h[:, None, 5]) / w - v
        misfit = np.where(weight > 0, np.hypot(misfit_u, misfit_v) * scale[:, None], 0.0)
    return centre + scale[:, None] * h[:, [2, 5]], misfit


def drop_isolated(board_xy: np.ndarray, ids: np.ndarray, corners: np.ndarray, scores: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A detection of at least `ISOLATION_MIN_CORNERS` corners without those that have fewer than `MIN_NEIGHBOURS`
    other detected corners within `LOCAL_SQUARES` squares of them on the board (their IDs come from the view's one
    homography far from the corners that fitted it, where a lens bends the board away from it); smaller detections
    unchanged. ``board_xy``: (C, 2) the board's corners; ``ids`` (N,), ``corners`` (N, 2), ``scores`` (N,).
    Returns (ids, corners, scores), order kept."""
    if len(ids) < ISOLATION_MIN_CORNERS:
        return ids, corners, scores
    keep = _near(_board_offsets(board_xy, ids, ids)).sum(axis=1) >= MIN_NEIGHBOURS
    return ids[keep], corners[keep], scores[keep]
