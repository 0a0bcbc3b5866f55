"""The marker reads', the cells' and the hypotheses' per-element loops compiled by numba: the same arithmetic and
decisions as their numpy paths (`marker_reader._squares_inside`, `marker_reader._square_maps`,
`marker_reader._reduce_reads`, `marker_reader.match_markers`, `lattice._nearest`, `lattice._cell_quads`,
`lattice.cell_homographies`, `lattice.squarest_cells`, `placement._square_sides`, `placement._agreement`,
`placement._support`), in one pass over the data instead of numpy's many passes and temporaries, which are most of
those paths' time on a frame's few thousand square reads (`docs/detector.md`, "A compiled decoder").

Imported only where numba is installed (``pip install deepcharuco[fast]``); the callers use the numpy paths
otherwise, and tests/detection/test_decode_kernel.py checks both give the same detections. The first call compiles (a few
seconds, cached on disk beside this file where it is writable).
"""

from __future__ import annotations

import numpy as np
from numba import njit, types
from numba.typed import Dict


@njit(cache=True)
def square_maps(homographies, local):
    """(R, 3, 3) float32 unit frames -> image, (P, 2) float32 points of the unit frame -> (x (R, P), y (R, P)) float32
    pixels, each point through each homography: (h00 x + h01 y + h02) / (h20 x + h21 y + h22), in float32, summed
    left to right as `marker_reader._square_maps` does."""
    count, points = homographies.shape[0], local.shape[0]
    x = np.empty((count, points), np.float32)
    y = np.empty((count, points), np.float32)
    for r in range(count):
        h = homographies[r]
        for p in range(points):
            u, v = local[p, 0], local[p, 1]
            w = h[2, 0] * u + h[2, 1] * v + h[2, 2]
            x[r, p] = (h[0, 0] * u + h[0, 1] * v + h[0, 2]) / w
            y[r, p] = (h[1, 0] * u + h[1, 1] * v + h[1, 2]) / w
    return x, y


@njit(cache=True, error_model="numpy")  # x / 0: inf or nan, as numpy gives it, not an exception
def squares_inside(homographies, width, height):
    """(R, 3, 3) float64 unit frames -> image -> (R,) bool: each square's corners (0, 0), (1, 0), (1, 1), (0, 1) in
    front of the camera (w > 0), finite and inside [0, width - 1] x [0, height - 1]; each coordinate summed
    h_j0 u + h_j1 v + h_j2 left to right, as `marker_reader._squares_inside`' matrix product gives it."""
    count = homographies.shape[0]
    inside = np.empty(count, np.bool_)
    for r in range(count):
        h = homographies[r]
        ok = True
        for corner in range(4):
            u = 1.0 if corner == 1 or corner == 2 else 0.0
            v = 1.0 if corner >= 2 else 0.0
            x = h[0, 0] * u + h[0, 1] * v + h[0, 2]
            y = h[1, 0] * u + h[1, 1] * v + h[1, 2]
            w = h[2, 0] * u + h[2, 1] * v + h[2, 2]
            px, py = x / w, y / w
            if not (w > 0 and np.isfinite(px) and np.isfinite(py) and px >= 0 and py >= 0
                    and px <= width - 1 and py <= height - 1):
                ok = False
                break
        inside[r] = ok
    return inside


@njit(cache=True)
def _median(values):
    """The median of a short 1-D float32 array, sorted in place (insertion sort: a few dozen values), as
    `marker_reader._row_medians` gives it (the float32 mean of the two middle values for an even count)."""
    for i in range(1, len(values)):
        value = values[i]
        j = i - 1
        while j >= 0 and values[j] > value:
            values[j + 1] = values[j]
            j -= 1
        values[j + 1] = value
    half = len(values) // 2
    if len(values) % 2:
        return values[half]
    return (values[half - 1] + values[half]) / np.float32(2)


@njit(cache=True)
def reduce_reads(values, grid, samples):
    """(R, P) float32 samples of `marker_reader._sample_grid`'s points (each bit cell's ``samples`` in row-major cell
    order, then the paper ring) -> (bits (R, grid, grid) float32: each cell's mean sample, summed in order; dark (R,)
    float32: the median of the border cells; bright (R,) float32: the median of the ring's samples)."""
    count = values.shape[0]
    ring_start = grid * grid * samples
    ring_count = values.shape[1] - ring_start
    bits = np.empty((count, grid, grid), np.float32)
    dark = np.empty(count, np.float32)
    bright = np.empty(count, np.float32)
    border = np.empty(4 * grid - 4, np.float32)
    ring = np.empty(ring_count, np.float32)
    for r in range(count):
        for cell in range(grid * grid):
            total = values[r, cell * samples]
            for k in range(1, samples):
                total = total + values[r, cell * samples + k]
            bits[r, cell // grid, cell % grid] = total / np.float32(samples)
        b = 0
        for col in range(grid):
            border[b] = bits[r, 0, col]
            border[b + 1] = bits[r, grid - 1, col]
            b += 2
        for row in range(1, grid - 1):
            border[b] = bits[r, row, 0]
            border[b + 1] = bits[r, row, grid - 1]
            b += 2
        dark[r] = _median(border)
        for k in range(ring_count):
            ring[k] = values[r, ring_start + k]
        bright[r] = _median(ring)
    return bits, dark, bright


@njit(cache=True)
def squarest_keep(sides, cosine, area, order, squarer_by, same_area, contained_area):
    """`lattice._squarest_keep` compiled: (Q, 4) int64 each quad's directed sides as compact IDs (0 .. S-1), (Q,)
    float64 largest |cos| of a corner angle and area, (Q,) the visiting order (squarest first) -> (Q,) bool kept."""
    quads = sides.shape[0]
    side_ids = 0
    for q in range(quads):
        for s in range(4):
            side_ids = max(side_ids, sides[q, s] + 1)
    # the quads kept on each directed side, as linked lists: head[side] -> entry, entry -> (quad, next entry)
    head = np.full(side_ids, -1, np.int64)
    entry_quad = np.empty(4 * quads, np.int64)
    entry_next = np.empty(4 * quads, np.int64)
    entries = 0
    keep = np.zeros(quads, np.bool_)
    for q in order:
        squarer, own, size = cosine[q] - squarer_by, area[q], same_area * area[q]
        beaten = False
        for s in range(4):
            e = head[sides[q, s]]
            while e >= 0 and not beaten:
                r = entry_quad[e]
                if cosine[r] < squarer and abs(area[r] - own) <= size:
                    beaten = True
                e = entry_next[e]
            if beaten:
                break
        if beaten:
            continue
        keep[q] = True
        for s in range(4):
            entry_quad[entries] = q
            entry_next[entries] = head[sides[q, s]]
            head[sides[q, s]] = entries
            entries += 1
    kept = keep.copy()
    for q in range(quads):
        if not kept[q]:
            continue
        smaller, squarer = contained_area * area[q], cosine[q] + squarer_by
        for s in range(4):
            e = head[sides[q, s]]
            while e >= 0 and keep[q]:
                r = entry_quad[e]
                if r != q and area[r] <= smaller and cosine[r] <= squarer:
                    keep[q] = False
                e = entry_next[e]
    return keep


@njit(cache=True)
def cell_quads(points, near, min_side, max_side_ratio, min_sine, closure_tolerance):
    """`lattice.find_cells`' quads before their de-duplication, compiled: (N, 2) float64 ``points``, (N, k) int64
    each one's nearest others -> (P, 4) int64 quads (a, b, d, c) in the order its numpy path makes them (``a``, then
    its neighbour pairs (i < j) row by row), each right-handed, plausible (sides, their ratio, the sine of their
    angle) and closed by a neighbour ``d`` of ``a`` near b + c - a (the nearest, the first of equals)."""
    count, k = near.shape
    out = np.empty((count * k * max(k - 1, 0) // 2, 4), np.int64)
    found = 0
    for a in range(count):
        ax, ay = points[a, 0], points[a, 1]
        for i in range(k):
            for j in range(i + 1, k):
                b, c = near[a, i], near[a, j]
                abx, aby = points[b, 0] - ax, points[b, 1] - ay
                acx, acy = points[c, 0] - ax, points[c, 1] - ay
                if not abx * acy - aby * acx > 0:  # right-handed: (b - a) x (c - a) > 0
                    b, c = c, b
                    abx, aby, acx, acy = acx, acy, abx, aby
                side_ab, side_ac = np.sqrt(abx * abx + aby * aby), np.sqrt(acx * acx + acy * acy)
                shorter, longer = min(side_ab, side_ac), max(side_ab, side_ac)
                sine = abs(abx * acy - aby * acx) / max(side_ab * side_ac, 1e-9)
                if not (shorter >= min_side and longer <= max_side_ratio * shorter and sine > min_sine):
                    continue
                ex, ey = points[b, 0] + points[c, 0] - ax, points[b, 1] + points[c, 1] - ay
                d, gap = -1, np.inf
                for o in range(k):
                    q = near[a, o]
                    dx, dy = ex - points[q, 0], ey - points[q, 1]
                    distance = np.sqrt(dx * dx + dy * dy)
                    if distance < gap:
                        d, gap = q, distance
                if not gap <= closure_tolerance * shorter or d == a or d == b or d == c:
                    continue
                out[found, 0], out[found, 1], out[found, 2], out[found, 3] = a, b, d, c
                found += 1
    return out[:found]


@njit(cache=True, error_model="numpy")
def agreement(proposals, square_xy, hypotheses, reach):
    """`placement._agreement` compiled: (K, 3, 3) float64 ``proposals`` (board square units -> image), (K, 2) float64
    each one's square on the board, (H,) int64 the ``hypotheses`` among them, (K,) float64 ``reach`` (px) -> (H, K)
    bool: hypothesis h puts proposal k's square's centre, then its first corner, within k's reach of where k read them.
    Compared without a division (``|p - o w| < r |w|``): a point at infinity never lands."""
    count, tried = len(square_xy), len(hypotheses)
    observed = np.empty((count, 2, 2))  # each proposal's own centre and first corner, in pixels
    for k in range(count):
        p = proposals[k]
        for corner in range(2):
            u = square_xy[k, 0] + (0.5 if corner == 0 else 0.0)
            v = square_xy[k, 1] + (0.5 if corner == 0 else 0.0)
            w = p[2, 0] * u + p[2, 1] * v + p[2, 2]
            observed[k, corner, 0] = (p[0, 0] * u + p[0, 1] * v + p[0, 2]) / w
            observed[k, corner, 1] = (p[1, 0] * u + p[1, 1] * v + p[1, 2]) / w
    agrees = np.zeros((tried, count), np.bool_)
    for h in range(tried):
        p = proposals[hypotheses[h]]
        for k in range(count):
            lands = True
            for corner in range(2):
                u = square_xy[k, 0] + (0.5 if corner == 0 else 0.0)
                v = square_xy[k, 1] + (0.5 if corner == 0 else 0.0)
                w = p[2, 0] * u + p[2, 1] * v + p[2, 2]
                dx = (p[0, 0] * u + p[0, 1] * v + p[0, 2]) - observed[k, corner, 0] * w
                dy = (p[1, 0] * u + p[1, 1] * v + p[1, 2]) - observed[k, corner, 1] * w
                if not dx * dx + dy * dy < (reach[k] * w) ** 2:
                    lands = False
                    break
            agrees[h, k] = lands
    return agrees


@njit(cache=True, error_model="numpy")
def cell_homographies(x, y):
    """`lattice.cell_homographies` compiled: (Q, 4) float64 corner x and y of each cell -> (Q, 3, 3) unit square ->
    image maps, by the same closed form in the same order of operations (a degenerate quad: not finite)."""
    count = x.shape[0]
    maps = np.empty((count, 3, 3))
    for q in range(count):
        x0, x1, x2, x3 = x[q, 0], x[q, 1], x[q, 2], x[q, 3]
        y0, y1, y2, y3 = y[q, 0], y[q, 1], y[q, 2], y[q, 3]
        dx1, dx2, dx3 = x1 - x2, x3 - x2, x0 - x1 + x2 - x3
        dy1, dy2, dy3 = y1 - y2, y3 - y2, y0 - y1 + y2 - y3
        det = dx1 * dy2 - dx2 * dy1
        g = (dx3 * dy2 - dx2 * dy3) / det
        h = (dx1 * dy3 - dx3 * dy1) / det
        maps[q, 0, 0], maps[q, 0, 1], maps[q, 0, 2] = x1 - x0 + g * x1, x3 - x0 + h * x3, x0
        maps[q, 1, 0], maps[q, 1, 1], maps[q, 1, 2] = y1 - y0 + g * y1, y3 - y0 + h * y3, y0
        maps[q, 2, 0], maps[q, 2, 1], maps[q, 2, 2] = g, h, 1.0
    return maps


@njit(cache=True)
def squarest_cells_keep(points, quads, squarer_by, same_area, contained_area):
    """`lattice.squarest_cells`' choice compiled whole: (N, 2) float64 ``points``, (Q, 4) int64 ``quads`` -> (Q,) bool
    kept. Each quad's largest |cos| of a corner angle and its area as `lattice.squarest_cells` computes them (the
    same operations in the same order), its directed sides as compact IDs, visited squarest first (a stable sort),
    then `squarest_keep`."""
    count = quads.shape[0]
    cosine = np.empty(count)
    area = np.empty(count)
    sides = np.empty((count, 4), np.int64)
    ids = Dict.empty(key_type=types.int64, value_type=types.int64)
    base = quads.max() + 1
    for q in range(count):
        largest, twice_area = 0.0, 0.0
        for i in range(4):
            here, after, before = quads[q, i], quads[q, (i + 1) % 4], quads[q, (i + 3) % 4]
            ax, ay = points[after, 0] - points[here, 0], points[after, 1] - points[here, 1]
            bx, by = points[before, 0] - points[here, 0], points[before, 1] - points[here, 1]
            value = abs(ax * bx + ay * by) / max(np.sqrt(ax * ax + ay * ay) * np.sqrt(bx * bx + by * by), 1e-12)
            largest = value if i == 0 else max(largest, value)
            twice_area += points[here, 0] * points[after, 1] - points[after, 0] * points[here, 1]
            key = here * base + after
            if key not in ids:
                ids[key] = len(ids)
            sides[q, i] = ids[key]
        cosine[q] = largest
        area[q] = 0.5 * abs(twice_area)
    order = np.argsort(cosine, kind="mergesort")
    return squarest_keep(sides, cosine, area, order, squarer_by, same_area, contained_area)


@njit(cache=True, error_model="numpy")
def square_sides(squares):
    """`placement._square_sides` compiled: (R, 3, 3) float64 unit-square frames -> (R,) the square root of each
    square's area in the image (its four corners through the frame, then the shoelace), the same operations in order."""
    count = squares.shape[0]
    sides = np.empty(count)
    xs, ys = np.empty(4), np.empty(4)
    for r in range(count):
        h = squares[r]
        for i in range(4):
            u, v = (0.0, 1.0, 1.0, 0.0)[i], (0.0, 0.0, 1.0, 1.0)[i]
            w = u * h[2, 0] + v * h[2, 1] + 1.0 * h[2, 2]
            xs[i] = (u * h[0, 0] + v * h[0, 1] + 1.0 * h[0, 2]) / w
            ys[i] = (u * h[1, 0] + v * h[1, 1] + 1.0 * h[1, 2]) / w
        twice_area = 0.0
        for i in range(4):
            j = (i + 1) % 4
            twice_area += xs[i] * ys[j] - xs[j] * ys[i]
        sides[r] = np.sqrt(0.5 * abs(twice_area))
    return sides


@njit(cache=True)
def nearest(points, k):
    """`lattice._nearest` compiled: (N, 2) float64 points -> (N, k) int64 each point's k nearest others, nearest first,
    equal distances by index. Every pair measured (N <= `placement.SEARCH_CANDIDATES`, 300) as `lattice._nearest_of`
    measures it, sqrt(dx * dx + dy * dy), and kept in a sorted list of k: a later index goes after an equal distance."""
    count = points.shape[0]
    near = np.empty((count, k), np.int64)
    kept = np.empty(k)
    for i in range(count):
        filled = 0
        for j in range(count):
            if j == i:
                continue
            dx, dy = points[i, 0] - points[j, 0], points[i, 1] - points[j, 1]
            distance = np.sqrt(dx * dx + dy * dy)
            if filled == k and not distance < kept[k - 1]:
                continue
            at = min(filled, k - 1)  # the last place, or the first free one; then moved up past every farther one
            while at > 0 and kept[at - 1] > distance:
                kept[at], near[i, at] = kept[at - 1], near[i, at - 1]
                at -= 1
            kept[at], near[i, at] = distance, j
            filled = min(filled + 1, k)
    return near


@njit(cache=True)
def _block_sum(values, start, count):
    """numpy's pairwise sum of ``values[start:start + count]`` for ``count`` <= 128: in order below 8 values, else eight
    running sums, combined in pairs, then the rest in order."""
    if count < 8:
        total = 0.0
        for i in range(count):
            total += values[start + i]
        return total
    r = values[start:start + 8].copy()
    i = 8
    while i < count - count % 8:
        for j in range(8):
            r[j] += values[start + i + j]
        i += 8
    total = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
    while i < count:
        total += values[start + i]
        i += 1
    return total


@njit(cache=True)
def _half_sum(values, start, count):
    """One half of `_pairwise_sum`'s: numpy's pairwise sum of up to 256 values (two blocks above 128)."""
    if count <= 128:
        return _block_sum(values, start, count)
    half = count // 2 - (count // 2) % 8
    return _block_sum(values, start, half) + _block_sum(values, start + half, count - half)


@njit(cache=True)
def _pairwise_sum(values, start, count):
    """The sum of ``values[start:start + count]`` (float64) as numpy's ``add.reduce`` sums a contiguous row (pairwise:
    eight running sums in blocks of up to 128, halves above: the first half a multiple of 8), so that it is the same
    number to the last bit, up to 512 values (the distinct markers of one view; beyond, halves of more than 256 are
    summed as two blocks: the same to rounding). Written out, not recursive: a recursive version, loaded from
    numba's cache by a second process, crashed it (docs/detector.md, fourteenth session)."""
    if count <= 128:
        return _block_sum(values, start, count)
    half = count // 2 - (count // 2) % 8
    return _half_sum(values, start, half) + _half_sum(values, start + half, count - half)


@njit(cache=True)
def support(marker, ncc, agrees, markers):
    """`placement._support` compiled: (K,) int64 ``marker`` (each in 0 .. ``markers`` - 1), (K,) float64 ``ncc``, (H, K)
    bool ``agrees`` -> (H,) each hypothesis' evidence: the best correlation (at least 0) of each distinct marker among
    its agreeing proposals, summed over the distinct markers in increasing order (as numpy sums a row)."""
    rank = np.full(markers, -1, np.int64)
    for k in range(len(marker)):
        rank[marker[k]] = 0
    distinct = 0
    for m in range(markers):
        if rank[m] == 0:
            rank[m] = distinct
            distinct += 1
    tried = agrees.shape[0]
    out = np.empty(tried)
    best = np.empty(distinct)
    for h in range(tried):
        best[:] = 0.0
        for k in range(len(marker)):
            if agrees[h, k]:
                value = max(ncc[k], 0.0)
                r = rank[marker[k]]
                if value > best[r]:
                    best[r] = value
        out[h] = _pairwise_sum(best, 0, distinct)
    return out


@njit(cache=True)
def best_pairs(ncc, per_read, floor):
    """`marker_reader.match_markers`' choice compiled: (R, C) float64 scores of each read against each (marker, turn)
    -> (read (K,), column (K,), score (K,)): each read's ``per_read`` best columns, best first, equal scores by the
    lower column, those scoring >= ``floor``; reads in order."""
    reads, columns = ncc.shape
    per_read = min(per_read, columns)
    out_read = np.empty(reads * per_read, np.int64)
    out_column = np.empty(reads * per_read, np.int64)
    out_score = np.empty(reads * per_read)
    best = np.empty(per_read, np.int64)
    found = 0
    for r in range(reads):
        filled = 0
        for c in range(columns):
            value = ncc[r, c]
            if filled == per_read and not value > ncc[r, best[per_read - 1]]:
                continue
            at = min(filled, per_read - 1)  # the last place, or the first free one; then up past every lower score
            while at > 0 and ncc[r, best[at - 1]] < value:
                best[at] = best[at - 1]
                at -= 1
            best[at] = c
            filled = min(filled + 1, per_read)
        for i in range(filled):
            score = ncc[r, best[i]]
            if score >= floor:
                out_read[found], out_column[found], out_score[found] = r, best[i], score
                found += 1
    return out_read[:found], out_column[:found], out_score[:found]
