"""Chessboard cells from corner candidates, whatever the board.

A ChArUco board's inner corners are X-junctions on a square lattice. Four of them bound each
square: corner ``a``, its neighbours ``b`` and ``c`` along the two lattice directions and ``d``
opposite ``a``, where ``d`` lies close to ``b + c - a`` (a parallelogram; perspective bends
this by a little over one square). `find_cells` finds such quads among the candidates of a
corner detector that knows nothing of the board; which square of which board each quad is,
is for the markers around it to say (`marker_reader`, `placement`). The lattice closes quads that are
no cell as well (halves of two cells, two or four cells): `squarest_cells` keeps the likeliest cells,
which the markers are read in first.

A cell's quad is ordered (a, b, d, c): unit-square corners (0, 0), (1, 0), (1, 1), (0, 1),
with ``cross(b - a, c - a) > 0`` in image coordinates (x right, y down). A board seen from
its printed side maps its own X (right) and Y (down) axes the same way round, so a cell's
unit frame differs from the board's square frame by a rotation of 0-3 quarter turns only.
"""

from __future__ import annotations

import numpy as np

from deepcharuco.core.vectors import lengths, pairwise_distances

try:  # `find_cells`' and `squarest_cells`' loops compiled (pip install deepcharuco[fast]); else numpy's, the same cells
    import deepcharuco.detection.markers.decode_kernel as compiled_kernel
except ImportError:
    compiled_kernel = None

NEIGHBOURS = 8  # nearest candidates a corner pairs up: its 4 lattice neighbours and 4 diagonals
NEAREST_EXTRA = 4  # `_nearest` asks its tree for this many more, so that a tie at the k-th rarely needs every point
# Fewer points are measured against each other: the tree's fixed cost (~0.15 ms) is more than that below ~64-96 points;
# at 300 (`placement.SEARCH_CANDIDATES`) the tree takes a fifth of the time (this 2-core EPYC, 2026-11-28).
TREE_FROM_POINTS = 64
# d may miss b + c - a by this fraction of the shorter side (perspective, lens distortion, jitter).
CLOSURE_TOLERANCE = 0.25
MAX_SIDE_RATIO = 2.5  # sides of one cell: foreshortening stretches them, not beyond this
MIN_SIDE_PX = 4.0  # smaller squares hold markers too small to read
MIN_SINE = 0.3  # a cell's corner angle is at least asin(0.3), ~17 degrees, from a straight line
# A quad gives way to a rival on one of its sides that is squarer by this much (`squarest_cells`): a square's sheared
# rival is 0.71 less square, a real cell's under a view steep enough to shear it to 69 degrees only 0.2.
SQUARER_BY = 0.2
SAME_AREA = 0.3  # ... of about the same area (a quad of two cells is as square as a real one under some views)
CONTAINED_AREA = 0.6  # a quad of two or more cells: one that shares its side is at most this fraction of its area


def find_cells(pixels: np.ndarray) -> np.ndarray:
    """(N, 2) candidate pixels -> (Q, 4) int64 candidate indices (a, b, d, c) of chessboard cells.

    Each cell appears once (its four corners as a set); cells may overlap when candidates are
    wrong: the markers they frame decide which are real.
    """
    points = np.asarray(pixels, np.float64).reshape(-1, 2)
    count = len(points)
    if count < 4:
        return np.zeros((0, 4), np.int64)
    k = min(NEIGHBOURS, count - 1)
    near = _nearest(points, k)  # (N, k)
    if compiled_kernel is not None:
        quads = compiled_kernel.cell_quads(points, near, MIN_SIDE_PX, MAX_SIDE_RATIO, MIN_SINE, CLOSURE_TOLERANCE)
    else:
        quads = _cell_quads(points, near)
    if len(quads) == 0:
        return np.zeros((0, 4), np.int64)
    # Each cell once, whichever corner it was found from: its sorted corners as one integer key (rows beyond int64).
    corners = np.sort(quads, axis=1).astype(np.int64)
    if count < 2 ** 15:
        _, unique = np.unique(corners @ (count ** np.arange(3, -1, -1, dtype=np.int64)), return_index=True)
    else:
        _, unique = np.unique(corners, axis=0, return_index=True)
    return quads[np.sort(unique)].astype(np.int64)


def _cell_quads(points: np.ndarray, near: np.ndarray) -> np.ndarray:
    """`find_cells`' quads before their de-duplication, by numpy: (N, 2) points, (N, k) each one's nearest others ->
    (P, 4) quads (a, b, d, c) (`decode_kernel.cell_quads` makes the same, compiled)."""
    count, k = near.shape
    first, second = np.triu_indices(k, 1)
    a = np.repeat(np.arange(count), len(first))
    b, c = near[:, first].ravel(), near[:, second].ravel()
    ab, ac = points[b] - points[a], points[c] - points[a]
    cross = ab[:, 0] * ac[:, 1] - ab[:, 1] * ac[:, 0]
    b, c = np.where(cross > 0, b, c), np.where(cross > 0, c, b)  # right-handed: (b - a) x (c - a) > 0
    ab, ac = points[b] - points[a], points[c] - points[a]
    side_ab, side_ac = lengths(ab), lengths(ac)
    shorter = np.minimum(side_ab, side_ac)
    sine = np.abs(ab[:, 0] * ac[:, 1] - ab[:, 1] * ac[:, 0]) / np.maximum(side_ab * side_ac, 1e-9)
    plausible = ((shorter >= MIN_SIDE_PX) & (np.maximum(side_ab, side_ac) <= MAX_SIDE_RATIO * shorter)
                 & (sine > MIN_SINE))
    a, b, c, shorter = a[plausible], b[plausible], c[plausible], shorter[plausible]
    expected = points[b] + points[c] - points[a]
    # d is a's diagonal neighbour: look for it among a's nearest candidates only, O(P k) not O(P N).
    options = near[a]  # (P, k)
    gap = lengths(expected[:, None] - points[options])
    nearest = gap.argmin(axis=1)
    d = options[np.arange(len(options)), nearest]
    closes = gap[np.arange(len(d)), nearest] <= CLOSURE_TOLERANCE * shorter
    quads = np.stack([a, b, d, c], axis=1)[closes]
    return quads[(quads[:, 2] != quads[:, 0]) & (quads[:, 2] != quads[:, 1]) & (quads[:, 2] != quads[:, 3])]


def squarest_cells(pixels: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """(N, 2) candidate pixels, (Q, 4) quads (a, b, d, c) of `find_cells` -> those without a clearly squarer rival
    of about their size, order kept (`squarest_rows`' rows of ``quads``)."""
    return quads[squarest_rows(pixels, quads)]


def squarest_rows(pixels: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """(N, 2) candidate pixels, (Q, 4) quads (a, b, d, c) of `find_cells` -> (Q',) int64 rows of the quads without a
    clearly squarer rival of about their size, ascending.

    Walked a -> b -> d -> c -> a, right-handed quads that lie on the same side of a side walk it the same way: two
    quads that share a directed side overlap. A lattice's corners close sheared quads too (a, a + x, a + y,
    a - x + y: halves of two cells), about four for every real cell. A quad is dropped where a rival sharing one of
    its directed sides, its area within `SAME_AREA`, is squarer by `SQUARER_BY` (largest |cos| of a corner angle: 0
    for a rectangle; a square's sheared rival 0.71). The lattice alone cannot tell which is real: where a steep view
    shears the real cells below ~55 degrees, their sheared rivals are the squarer ones and the real cells go; the
    caller reads every quad when these find nothing (`placement.corners_from_markers`). Then a quad that shares a
    side with one at most `CONTAINED_AREA` its area and not less square by `SQUARER_BY` is dropped (two cells, or
    four: it holds a real cell)."""
    if len(quads) < 2:
        return np.arange(len(quads))
    points = np.asarray(pixels, np.float64).reshape(-1, 2)
    if compiled_kernel is not None:
        return np.flatnonzero(compiled_kernel.squarest_cells_keep(
            points, np.ascontiguousarray(quads, np.int64), SQUARER_BY, SAME_AREA, CONTAINED_AREA))
    corners = points[quads]  # (Q, 4, 2), around the quad
    ahead, behind = np.roll(corners, -1, axis=1) - corners, np.roll(corners, 1, axis=1) - corners
    cosine = (np.abs(np.sum(ahead * behind, axis=2)) / np.maximum(
        lengths(ahead) * lengths(behind), 1e-12)).max(axis=1)
    area = quad_areas(corners)
    # Each quad's four directed sides a -> b as integers a * n + b (n: one more than the largest index): (Q, 4).
    sides = quads * (int(quads.max()) + 1) + np.roll(quads, -1, axis=1)
    order = np.argsort(cosine, kind="stable")
    return np.flatnonzero(_squarest_keep(sides, cosine, area, order))


def _squarest_keep(sides: np.ndarray, cosine: np.ndarray, area: np.ndarray, order: np.ndarray) -> np.ndarray:
    """`squarest_cells`' choice in Python: (Q, 4) int64 each quad's directed sides, (Q,) float64 largest |cos| of a
    corner angle and area, (Q,) the order to visit them in (squarest first) -> (Q,) bool kept
    (`decode_kernel.squarest_keep` decides exactly this)."""
    sides, cosine, area = sides.tolist(), cosine.tolist(), area.tolist()
    kept: dict[int, list[int]] = {}  # the quads kept so far on each directed side (visited squarest first)
    keep = np.zeros(len(sides), bool)
    for q in order.tolist():
        rivals = [r for side in sides[q] if side in kept for r in kept[side]]  # most quads have none: no test
        if rivals:
            squarer, own, size = cosine[q] - SQUARER_BY, area[q], SAME_AREA * area[q]
            if any(cosine[r] < squarer and abs(area[r] - own) <= size for r in rivals):
                continue
        keep[q] = True
        for side in sides[q]:
            kept.setdefault(side, []).append(q)
    # Quads of two or four cells (squares of a lattice's diagonals, near the edge of the candidates) share a side with
    # a smaller quad as square as they are, which they contain.
    for q in np.flatnonzero(keep).tolist():
        smaller, squarer = CONTAINED_AREA * area[q], cosine[q] + SQUARER_BY
        keep[q] = not any(area[r] <= smaller and cosine[r] <= squarer for side in sides[q] for r in kept[side] if r != q)
    return keep


def quad_areas(corners: np.ndarray) -> np.ndarray:
    """(Q, 4, 2) quad corners in order around each quad -> (Q,) their areas (shoelace; pixels^2)."""
    x, y = corners[:, :, 0], corners[:, :, 1]
    return 0.5 * np.abs(np.sum(x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y, axis=1))


def _nearest(points: np.ndarray, k: int) -> np.ndarray:
    """(N, 2) points -> (N, k) indices of each point's k nearest others, nearest first, equal distances by index.

    Where numba is installed every pair is measured, compiled (`decode_kernel.nearest`: no tree to build). Else,
    above `TREE_FROM_POINTS` points a k-d tree (scipy's) finds a few more than k of each; where the k-th of them is as
    far as the farthest found, an equally far point may be among those it left out, and that row is measured against
    every point (`_nearest_of`). Candidates sit on whole pixels, so many distances are equal: the index settles them,
    the same way on every machine."""
    count = len(points)
    if compiled_kernel is not None:
        return compiled_kernel.nearest(np.ascontiguousarray(points, np.float64), k)
    reach = k + 1 + NEAREST_EXTRA  # itself, k others and a few beyond
    if count <= max(reach, TREE_FROM_POINTS):
        return _nearest_of(points, k, np.arange(count))
    rows = np.arange(count)
    from scipy.spatial import cKDTree  # here: importing scipy.spatial takes ~0.4 s, which a small search never needs

    _, found = cKDTree(points).query(points, reach)
    found = np.asarray(found, np.int64)
    distance = lengths(points[:, None] - points[found])  # as `_nearest_of` measures them, not the tree's own
    distance[found == rows[:, None]] = np.inf  # the point itself: last
    order = np.lexsort((found, distance), axis=1)  # by distance, then by index
    found, distance = np.take_along_axis(found, order, axis=1), np.take_along_axis(distance, order, axis=1)
    near = found[:, :k].copy()
    farthest = np.where(np.isinf(distance), -1.0, distance).max(axis=1)
    unsure = ~np.isinf(distance[:, -1]) | (distance[:, k - 1] >= farthest)  # itself not found (duplicates), or a tie
    if unsure.any():
        near[unsure] = _nearest_of(points, k, rows[unsure])
    return near


def _nearest_of(points: np.ndarray, k: int, rows: np.ndarray) -> np.ndarray:
    """`_nearest` of the points ``rows`` (R,) measured against every point: (R, k), in the same order."""
    distance = pairwise_distances(points[rows], points)
    distance[np.arange(len(rows)), rows] = np.inf
    return np.argsort(distance, axis=1, kind="stable")[:, :k]


def cell_homographies(pixels: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """(N, 2) pixels, (Q, 4) quads -> (Q, 3, 3) homographies from each cell's unit square to the image.

    The unit square's map has a closed form (Heckbert, "Fundamentals of Texture Mapping", 1989): no 8x8
    solve per cell. A degenerate quad (three corners on a line) gives a non-finite map."""
    if len(quads) == 0:
        return np.zeros((0, 3, 3))
    # float32 pixels, as the detector's candidates are; the map itself in float64.
    x, y = np.moveaxis(np.asarray(pixels, np.float32).astype(np.float64)[quads], -1, 0)  # each (Q, 4)
    if compiled_kernel is not None:
        return compiled_kernel.cell_homographies(np.ascontiguousarray(x), np.ascontiguousarray(y))
    (x0, x1, x2, x3), (y0, y1, y2, y3) = x.T, y.T
    dx1, dx2, dx3 = x1 - x2, x3 - x2, x0 - x1 + x2 - x3
    dy1, dy2, dy3 = y1 - y2, y3 - y2, y0 - y1 + y2 - y3
    maps = np.empty((len(quads), 3, 3))
    # A degenerate quad's g, h are infinite, and infinity times a corner at pixel 0 is NaN: both are its answer.
    with np.errstate(divide="ignore", invalid="ignore"):
        det = dx1 * dy2 - dx2 * dy1
        g = (dx3 * dy2 - dx2 * dy3) / det
        h = (dx1 * dy3 - dx3 * dy1) / det
        maps[:, 0] = np.stack([x1 - x0 + g * x1, x3 - x0 + h * x3, x0], axis=1)
        maps[:, 1] = np.stack([y1 - y0 + g * y1, y3 - y0 + h * y3, y0], axis=1)
    maps[:, 2] = np.stack([g, h, np.ones_like(g)], axis=1)
    return maps
