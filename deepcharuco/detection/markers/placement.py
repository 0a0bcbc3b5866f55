"""Where the board lies: markers read in chessboard cells vote for one view of the board.

    corner candidates -> cells (`lattice.find_cells`; the squarest of them first, `lattice.squarest_cells`, every
    cell where those find no verified view) -> each cell and its four edge neighbours
    read as markers (`marker_reader`) -> every marker matched to the board proposes a homography
    (its square's place on the board, the cell's frame, the quarter turn between them) -> the
    proposal most other matched markers agree with wins, if at least ``MIN_MARKERS`` distinct
    markers back it -> its homography, refitted on the backing squares, then on the corners it
    claims, predicts every corner; each takes the candidate found there (`board_check.assign_ids`).

Nothing here is board-specific training: any dictionary, size and layout reads the same way,
and a board of another layout or dictionary finds none of its markers among ours. Board units
are metres (``BoardSpec``'s frame); pixels OpenCV's.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.core.detection import corner_spacing, no_corners
from deepcharuco.core.vectors import homogeneous, lengths, pairwise_distances
from deepcharuco.detection.board_check import BoardView, apply_homography, assign_ids, in_image
from deepcharuco.detection.junction import pattern_evidence
from deepcharuco.detection.markers.lattice import cell_homographies, find_cells, quad_areas, squarest_rows
from deepcharuco.detection.markers.marker_reader import (QUARTER_TURNS, board_markers, match_markers,
                                                         read_squares)
from deepcharuco.detection.markers.settling import _fittable, _neighbourhoods, local_predictions
from deepcharuco.detection.markers.verification import (MIN_MARKERS, marker_view_verified, reading_image,
                                                        square_translations)
from deepcharuco.networks.cells import CellCandidates

try:  # the squares' sizes and the hypotheses' agreement compiled (pip install deepcharuco[fast]); else numpy's
    import deepcharuco.detection.markers.decode_kernel as compiled_kernel
except ImportError:
    compiled_kernel = None


# A video's board where the frame before put it (`view_near`): the view is moved by the median offset of the corners
# that have a candidate within NEAR_FRACTION of the corner spacing, at least MIN_NEAR of them (a board that moved
# farther is found by the search through the cells, as in any frame).
NEAR_FRACTION = 0.4
MIN_NEAR = 4


# ... and stands when it names NEAR_SHARE of the corners it puts in the image; else the cells are searched too, and the
# view naming more corners kept (a blurred board's view moved by the median offset may claim only some of them).
NEAR_SHARE = 0.9


# Corners the verified view predicts where no candidate reaches the detector's threshold may take a weaker one
# (point confidence >= `weak_confidence`, within WEAK_REACH_PX of the prediction): the markers already name the
# corner, the point head need only say that one is there.
WEAK_CONFIDENCE = 0.05
WEAK_REACH_PX = 3.0


# A network whose confidences run low (a distilled student in the dark: its corners at 0.02-0.1 where its teacher's
# are above 0.25) is given a threshold at or below WEAK_CONFIDENCE; its weak cells then start at WEAK_SHARE of it, so
# that some cells are still weak and take a corner only where their found neighbours place it (without any, one view
# fitted on a corner of a 22x22 board was carried across a wide lens and put a corner two squares off). Every
# threshold >= 2 x WEAK_CONFIDENCE, the shipped networks' among them, keeps WEAK_CONFIDENCE.
WEAK_SHARE = 0.5


def weak_confidence(threshold: float) -> float:
    """The point confidence a cell needs to fill in a corner of a verified view, for a detector's ``threshold``."""
    return min(WEAK_CONFIDENCE, WEAK_SHARE * float(threshold))


# Corners the verified view predicts where the point head gave no candidate at all (a cast shadow's edge across them
# silences it) are filled in where the board's printed pattern shows around the place their found neighbours put them
# (`junction.pattern_evidence` >= PATTERN_MIN_T, a t-statistic: the pattern's contrast on both sides of the best
# fitting shadow edge) and no found corner lies within PATTERN_APART corner spacings of it; the detector places them
# by the pattern (`junction.locate_by_pattern`), not RefineNet, which the shadow's edge pulls off. Validation (15
# boards of DICT_4X4/5X5/6X6, 5 inverted, none of the report's: data seeds 3101-3103 and 3201-3212, `evaluate.paper.sequences
# --only shadow-1 shadow-2 shadow-3 --frames 40`; and 131 family renders, `datagen.render --family
# DICT_4X4,DICT_5X5,DICT_6X6 --seed 9137 --n 150`, with occluders and lens distortion), without -> with:
# a shadow's edge drawn (`datagen.shadow_edge`) through each visible corner of the sequences' first frames, 909 in
# turn: that corner found 779 -> 799, right corners 22,496 -> 22,561, off (> 3 px) 4 -> 4; every second frame of the
# rendered shadow sequences: right 17,799 -> 17,802, off 6 -> 6; the renders: right 5,903 -> 5,929, off 87 -> 87.
# 12 is the lowest threshold at which no set gains a wrong corner (fill-ins tried at 0, by their evidence: at 10 the
# renders gain 1, 3.6 px off under a k1 = -0.31 lens, at 8 two, at 3 eight; corners the point head found score
# 17-170 in well-lit validation frames). Without the spacing rule a fill-in carried past a wide lens' bent board edge
# took a found corner's place, one diagonal away (the same checker there: 18.8).
PATTERN_MIN_T = 12.0
PATTERN_APART = 0.5
PATTERN_SCORE = 0.0  # the score of a corner placed by the pattern: the point head gave it no evidence
LOCAL_FIT_PX = 2.0  # ... when those corners fit their homography this well (cell pixels: integer, +-1 px)
SEARCH_CANDIDATES = 300  # corners the view is searched among, most confident first: bounds the time on noise
MAX_CELLS = 600  # cells read at most (300 corners frame about 300 cells)
HYPOTHESES = 256  # proposals tried as the board's view, best correlated first
AGREEMENT = 0.3  # two markers agree when one's view puts the other's square within this many square sides


# A cell's edge neighbours: the markers of a ChArUco board sit in the squares next to the black ones.
NEIGHBOUR_OFFSETS = np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]], np.float64)
NEIGHBOUR_OFFSETS.flags.writeable = False


@dataclass(frozen=True)
class MarkerView:
    """A board view backed by markers: ``view`` (homography board metres -> pixels), ``marker_ids``
    (distinct marker IDs that back it) and ``reads`` (how many square reads matched those markers)."""

    view: BoardView
    marker_ids: np.ndarray
    reads: int


class CellReads:
    """The marker reads of each cell's five squares (the cell and its edge neighbours, `NEIGHBOUR_OFFSETS`), kept by
    the cell's row in one list of ``cells`` cells (`lattice.find_cells`' list of a search): `corners_from_markers`'
    second pass through the cells (every one) reads only those its first (the squarest, rows of the same list) did
    not. A square's read depends on its cell's corners alone, so a kept read is the read it would make again. For one
    image, one reader and one set of candidate pixels."""

    def __init__(self, cells: int):
        self.have = np.zeros(cells, bool)
        self.bits: np.ndarray | None = None  # (cells, 5, n, n) float32, allocated at the first read
        self.contrast = np.zeros((cells, len(NEIGHBOUR_OFFSETS)), np.float32)

    def read(self, rows: np.ndarray, read: callable) -> tuple[np.ndarray, np.ndarray]:
        """(Q,) rows of cells -> (bits (Q * 5, n, n), contrast (Q * 5,)) as `read_squares` gives them, cell by cell;
        ``read(new)`` reads the squares of the cells ``new`` (Q,) bool among ``rows`` not read before."""
        new = ~self.have[rows]
        if new.any():
            bits, contrast = read(new)
            side = len(NEIGHBOUR_OFFSETS)
            if self.bits is None:
                self.bits = np.empty((len(self.have), side, *bits.shape[1:]), np.float32)
            self.bits[rows[new]] = bits.reshape(-1, side, *bits.shape[1:])
            self.contrast[rows[new]] = contrast.reshape(-1, side)
            self.have[rows[new]] = True
        return self.bits[rows].reshape(-1, *self.bits.shape[2:]), self.contrast[rows].reshape(-1)


def find_marker_view(gray: np.ndarray, board: BoardSpec, pixels: np.ndarray, quads: np.ndarray,
                     read_gray: np.ndarray | None = None, reader: str | None = None, reads: CellReads | None = None,
                     rows: np.ndarray | None = None) -> MarkerView | None:
    """The view of ``board`` that the markers in the cells ``quads`` (Q, 4) (`lattice.find_cells`) between
    ``pixels`` (N, 2) corner candidates agree on, or None.

    ``gray``: (H, W) uint8 in the board's canonical appearance (`print_face.canonical_view`), the image
    ``pixels`` (most confident first) were found in; ``read_gray``: the same image at a higher resolution to read the markers in
    (default ``gray``); ``reader``: `marker_reader.READERS` (default theirs); ``reads``: reads of cells made before in
    the same image by the same reader among the same ``pixels``, reused and added to, with ``rows`` (Q,) the cells'
    rows in the list ``reads`` keeps them by. The view returned maps to ``gray``'s pixels."""
    if len(quads) == 0:
        return None
    if len(quads) > MAX_CELLS:  # pixels come most confident first: keep the cells of the most confident corners
        kept = np.argsort(quads.max(axis=1), kind="stable")[:MAX_CELLS]
        quads, rows = quads[kept], None if rows is None else rows[kept]
    cells = cell_homographies(pixels, quads)  # (Q, 3, 3) unit square -> image
    # Every cell and its edge neighbours: (Q * 5) squares, each with its own unit frame. The same square is read from
    # up to five cells: each read is one more vote, and a square badly extrapolated from one cell is read well from
    # another.
    squares = _neighbour_squares(cells).reshape(-1, 3, 3)
    markers = board_markers(board)
    read_gray, to_read = reading_image(gray, read_gray)
    if reads is None or rows is None:
        bits, contrast = read_squares(read_gray, to_read @ squares, markers.size, markers.ratio, reader)
    else:
        by_cell = squares.reshape(len(quads), len(NEIGHBOUR_OFFSETS), 3, 3)
        bits, contrast = reads.read(rows, lambda new: read_squares(
            read_gray, to_read @ by_cell[new].reshape(-1, 3, 3), markers.size, markers.ratio, reader))
    matches = match_markers(bits, contrast, markers, reader=reader)
    if _distinct_count(matches.marker, len(markers.ids)) < MIN_MARKERS:
        return None
    # Each proposal: board square units -> image, via its square's frame and the quarter turn.
    square_xy = markers.squares[matches.marker].astype(np.float64)
    proposals = squares[matches.read] @ QUARTER_TURNS[matches.turn] @ square_translations(-square_xy)
    # Proposal i agrees with proposal j when it puts j's square where j was read, the same way round:
    # compare the square's centre and its first corner. Only the best-correlated proposals are tried
    # as the view (the right view has many proposals, so some among the best): O(HYPOTHESES x K).
    hypotheses = np.argsort(-matches.ncc, kind="stable")[:HYPOTHESES]
    reach = AGREEMENT * _square_sides(squares[matches.read])  # (K,)
    agrees = (compiled_kernel.agreement(proposals, square_xy, hypotheses.astype(np.int64), reach)
              if compiled_kernel is not None else _agreement(proposals, square_xy, hypotheses, reach))
    support = (compiled_kernel.support(matches.marker.astype(np.int64), matches.ncc.astype(np.float64), agrees,
                                       len(markers.ids))
               if compiled_kernel is not None else _support(matches.marker, matches.ncc, agrees))
    best = int(np.argmax(support))
    if _distinct_count(matches.marker[agrees[best]], len(markers.ids)) < MIN_MARKERS:
        return None
    backing = np.flatnonzero(agrees[best])
    # Refit on the backing squares' four corners each (board square units -> image).
    unit = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float64)
    board_points = (square_xy[backing][:, None] + unit[None]).reshape(-1, 2)
    image_points = _apply_each(np.repeat(proposals[backing], 4, axis=0), board_points)
    homography, _ = cv2.findHomography(board_points, image_points, 0)
    if homography is None:
        return None
    to_metres = np.diag([1.0 / board.square_length, 1.0 / board.square_length, 1.0])
    view = BoardView(homography=homography @ to_metres, inliers=np.ones(len(board_points), bool))
    return MarkerView(view=view, marker_ids=np.unique(markers.ids[matches.marker[backing]]), reads=len(backing))


def _neighbour_squares(cells: np.ndarray) -> np.ndarray:
    """(Q, 3, 3) cell frames (unit square -> image) -> (Q, 5, 3, 3): each cell's frame moved by each of
    `NEIGHBOUR_OFFSETS` (d) in the unit frame, H @ [[1, 0, dx], [0, 1, dy], [0, 0, 1]]: the first two columns are the
    cell's, the third h0 dx + h1 dy + h2, summed in the order a matrix product sums it (the offsets are 0 and +-1, so
    every product is exact). A degenerate cell's frame (not finite) gives NaN squares, which no read takes."""
    cells = np.where(np.isfinite(cells).all(axis=(1, 2))[:, None, None], cells, np.nan)  # inf x 0 would warn
    dx, dy = NEIGHBOUR_OFFSETS[:, 0, None], NEIGHBOUR_OFFSETS[:, 1, None]  # (5, 1): broadcast over the rows
    squares = np.empty((len(cells), len(NEIGHBOUR_OFFSETS), 3, 3))
    squares[:, :, :, :2] = cells[:, None, :, :2]
    squares[:, :, :, 2] = cells[:, None, :, 0] * dx + cells[:, None, :, 1] * dy + cells[:, None, :, 2]
    return squares


def _distinct_count(marker: np.ndarray, count: int) -> int:
    """How many distinct values ``marker`` (K,) int, each in 0 .. ``count`` - 1, holds."""
    seen = np.zeros(count, bool)
    seen[marker] = True
    return int(np.count_nonzero(seen))


def _agreement(proposals: np.ndarray, square_xy: np.ndarray, hypotheses: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """(K, 3, 3) proposals (board square units -> image), (K, 2) each one's square, (H,) the hypotheses among them,
    (K,) reach (px) -> (H, K) bool: hypothesis h puts proposal k's square's centre, then its first corner, within k's
    reach of where k read them (`decode_kernel.agreement` decides the same, compiled)."""
    # A far-off proposal may send a point to infinity. The centres first, for every (hypothesis, proposal) pair:
    # (H, K); the first corners then only for the pairs whose centres agree (0.3-5 % of them on the report's boards).
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        centres = homogeneous(square_xy + 0.5)
        # (H, 3, K): one matrix product for all hypotheses (a stacked matmul of H 3x3s is 2x slower, same numbers).
        mapped = (proposals[hypotheses].reshape(-1, 3) @ centres.T).reshape(len(hypotheses), 3, -1)
        agrees = _lands_within(mapped, _apply_each(proposals, centres[:, :2]), reach)
        pair_h, pair_k = np.nonzero(agrees)
        firsts = homogeneous(square_xy)
        mapped = np.einsum("nij,nj->ni", proposals[hypotheses[pair_h]], firsts[pair_k])[:, :, None]  # (n, 3, 1)
        observed = _apply_each(proposals, square_xy)[pair_k][:, None]  # (n, 1, 2)
        agrees[pair_h, pair_k] = _lands_within(mapped, observed, reach[pair_k][:, None])[:, 0]
    return agrees


def _support(marker: np.ndarray, ncc: np.ndarray, agrees: np.ndarray) -> np.ndarray:
    """The evidence of each hypothesis' agreeing proposals: ``marker``, ``ncc`` (K,) per proposal, ``agrees``
    (H, K) bool -> (H,): each distinct marker counts once, by its best correlation (at least 0)
    (`decode_kernel.support` computes the same numbers, compiled)."""
    distinct, rank = np.unique(marker, return_inverse=True)
    # Few pairs agree (the centres' test leaves 0.3-5 %): the best per (hypothesis, marker) over those pairs only.
    hypothesis, proposal = np.nonzero(agrees)
    best = np.zeros((len(agrees), len(distinct)))
    np.maximum.at(best, (hypothesis, rank[proposal]), np.maximum(ncc[proposal].astype(np.float64), 0.0))
    return best.sum(axis=1)


def _lands_within(mapped: np.ndarray, observed: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """(A, 3, K) homogeneous points, (K, 2) or (A, K, 2) pixels, (K,) or (A, K) distances -> (A, K) bool: whether each
    point lands within its distance of its pixel. Compared as |p - o w| < r |w|, which is |p / w - o| < r without
    the division (a point at infinity, w = 0, or a pixel that is not finite never lands)."""
    w = mapped[:, 2]
    dx = mapped[:, 0] - observed[..., 0] * w
    dy = mapped[:, 1] - observed[..., 1] * w
    return dx * dx + dy * dy < (reach * w) ** 2


def _square_sides(squares: np.ndarray) -> np.ndarray:
    """(R, 3, 3) unit-square frames -> (R,) square root of each square's area in the image (pixels)
    (`decode_kernel.square_sides` computes the same, compiled)."""
    if compiled_kernel is not None:
        return compiled_kernel.square_sides(np.ascontiguousarray(squares, np.float64))
    unit = np.array([[0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], np.float64)
    corners = unit @ np.transpose(squares, (0, 2, 1))  # (R, 4, 3)
    return np.sqrt(quad_areas(corners[:, :, :2] / corners[:, :, 2:]))


def _apply_each(homographies: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(K, 3, 3) homographies, (K, 2) points -> (K, 2): each point through its own homography."""
    mapped = np.einsum("kij,kj->ki", homographies, homogeneous(xy))
    return mapped[:, :2] / mapped[:, 2:]


def view_near(expected: np.ndarray, board_xy: np.ndarray, pixels: np.ndarray) -> BoardView | None:
    """The view ``expected`` (3x3, board metres -> pixels: where the board was a frame ago) moved by the median offset
    from its predicted corners to their nearest ``pixels`` (N, 2) candidates, or None where fewer than `MIN_NEAR`
    corners have a candidate within `NEAR_FRACTION` of the corner spacing (the board moved too far, or is gone)."""
    predicted, w = apply_homography(expected, np.asarray(board_xy, np.float64))
    if len(pixels) < MIN_NEAR or not (w > 0).all():
        return None
    distance = pairwise_distances(predicted, pixels.astype(np.float64))  # (C, N)
    nearest = distance.argmin(axis=1)
    reach = NEAR_FRACTION * corner_spacing(predicted)
    close = distance[np.arange(len(predicted)), nearest] <= reach
    if close.sum() < MIN_NEAR:
        return None
    offset = np.median(pixels[nearest[close]] - predicted[close], axis=0)
    moved = np.array([[1.0, 0.0, offset[0]], [0.0, 1.0, offset[1]], [0.0, 0.0, 1.0]]) @ expected
    return BoardView(homography=moved, inliers=np.ones(len(board_xy), bool))


def corners_from_markers(gray: np.ndarray, board: BoardSpec, candidates: CellCandidates, refits: int = 2,
                         read_gray: np.ndarray | None = None, reader: str | None = None,
                         threshold: float | None = None, expected: np.ndarray | None = None
                         ) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], MarkerView | None]:
    """The board's corners among ``candidates``, identified by the markers around them, in a view whose
    markers read as the board's own (`view_is_verified`).

    ``gray``: the canonical image the candidates were found in; ``read_gray``: the same image at full
    resolution, where the markers are read (default ``gray``); ``reader``: how (`marker_reader.READERS`);
    ``threshold``: the point confidence a candidate needs to find and fit the view (default: every
    candidate). Candidates below it (down to `weak_confidence`, as the caller chose them) only fill in
    the corners the verified view predicts where no confident candidate lies (`_fill_in`).

    Returns ((ids (K,), pixels (K, 2) float32, scores (K,) float32) strongest first, the marker view or
    None). The view's homography is refitted ``refits`` times on the corners it claimed (RANSAC), which
    follows a mildly distorted lens better than the markers' squares alone.

    ``expected``: (3, 3) board metres -> ``gray``'s pixels, where the board is expected (a video's frame before,
    `BoardTracker`): that view, moved onto the candidates (`view_near`), is tried first and stands when its markers
    read as the board's own, with every marker counted (none chose it); the search through the cells runs only
    where it does not."""
    weak = None
    if threshold is not None:
        confident = candidates.confidence >= threshold
        candidates, weak = candidates.subset(confident), candidates.subset(~confident)
    # The view is searched among the most confident corners only (an untrained or confused point head must
    # not cost seconds); every candidate may then take a corner the view predicts.
    strongest = candidates.pixels[np.argsort(-candidates.confidence, kind="stable")[:SEARCH_CANDIDATES]]
    board_xy = board.corner_points()[:, :2]
    near = None if expected is None else view_near(expected, board_xy, strongest)
    nearby = None
    if near is not None:
        found = MarkerView(view=near, marker_ids=np.zeros(0, np.int64), reads=0)
        verified = _verified_corners(gray, board, board_xy, candidates, found, refits, read_gray, reader)
        if verified is not None:
            nearby = _filled_in(gray, board, board_xy, verified, weak, found)
            in_view = in_image(nearby[1].view.homography, board_xy, gray.shape[::-1])[1].sum()
            if len(nearby[0][0]) >= NEAR_SHARE * in_view:
                return nearby
    searched = _searched(gray, board, board_xy, candidates, strongest, weak, refits, read_gray, reader)
    if nearby is not None and (searched[1] is None or len(searched[0][0]) < len(nearby[0][0])):
        return nearby
    return searched


def _searched(gray: np.ndarray, board: BoardSpec, board_xy: np.ndarray, candidates: CellCandidates,
              strongest: np.ndarray, weak: CellCandidates | None, refits: int, read_gray: np.ndarray | None,
              reader: str | None) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], MarkerView | None]:
    """`corners_from_markers`' search through the cells between the ``strongest`` candidates."""
    # The squarest cells first: about a quarter of the reads where the view is not steep (`lattice.squarest_cells`); every
    # cell where those find no verified view.
    every = find_cells(strongest)
    squarest = squarest_rows(strongest, every)
    reads = CellReads(len(every))  # the squarest cells' reads, reused when every cell is read
    refused = None
    for rows in (squarest, np.arange(len(every))) if len(squarest) < len(every) else (np.arange(len(every)),):
        found = find_marker_view(gray, board, strongest, every[rows], read_gray, reader, reads, rows)
        # Every cell's pass often settles on the view the squarest cells' pass found and the checks refused (45 of 79
        # such calls on caliscope's webcams, fast networks): the same view and markers, refused again unchecked.
        verified = None if found is None or _same_view(found, refused) else \
            _verified_corners(gray, board, board_xy, candidates, found, refits, read_gray, reader)
        if verified is not None:
            break
        refused = found
    else:
        return no_corners(), None
    return _filled_in(gray, board, board_xy, verified, weak, found)


def _same_view(found: MarkerView, other: MarkerView | None) -> bool:
    """Whether ``found`` is ``other``'s view, backed by the same markers: what `_verified_corners` reads of a view
    depends on nothing else."""
    return other is not None and np.array_equal(found.view.homography, other.view.homography) \
        and np.array_equal(found.marker_ids, other.marker_ids)


def _filled_in(gray: np.ndarray, board: BoardSpec, board_xy: np.ndarray,
               verified: tuple[tuple[np.ndarray, np.ndarray, np.ndarray], BoardView], weak: CellCandidates | None,
               found: MarkerView) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], MarkerView]:
    """`corners_from_markers`' result from its verified corners and view: the corners the view predicts where no
    confident candidate lies filled in from the ``weak`` ones and the printed pattern (None: none were set apart)."""
    (ids, pixels, scores), view = verified
    if weak is not None:
        height, width = gray.shape
        if len(weak):
            ids, pixels, scores = _fill_in(view, board_xy, (ids, pixels, scores), weak, (width, height))
        ids, pixels, scores = _fill_in_by_pattern(gray, board, view, board_xy, (ids, pixels, scores))
    return (ids, pixels, scores), MarkerView(view=view, marker_ids=found.marker_ids, reads=found.reads)


def _verified_corners(gray: np.ndarray, board: BoardSpec, board_xy: np.ndarray, candidates: CellCandidates,
                      found: MarkerView, refits: int, read_gray: np.ndarray | None, reader: str | None
                      ) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], BoardView] | None:
    """The corners among ``candidates`` that ``found``'s view names (``board_xy``: (C, 2) the board's corners), that
    view refitted ``refits`` times on them (RANSAC) -> ((ids, pixels, scores), the view), or None where its markers
    do not read as the board's own."""
    height, width = gray.shape
    ids, pixels, scores = assign_ids(found.view, board_xy, candidates, (width, height))
    view = found.view
    for _ in range(refits):
        if len(ids) < 6:
            break
        homography, mask = cv2.findHomography(board_xy[ids], pixels.astype(np.float64), cv2.RANSAC, 3.0)
        if homography is None:
            break
        view = BoardView(homography=homography, inliers=mask.ravel().astype(bool))
        claimed = ids, pixels
        ids, pixels, scores = assign_ids(view, board_xy, candidates, (width, height))
        if np.array_equal(ids, claimed[0]) and np.array_equal(pixels, claimed[1]):
            break  # the same corners again: a refit would repeat this one (OpenCV seeds its RANSAC)
    if not marker_view_verified(gray, board, view.homography, read_gray, reader, chosen_by=found.marker_ids):
        return None
    return (ids, pixels, scores), view


def _fill_in(view: BoardView, board_xy: np.ndarray, found: tuple[np.ndarray, np.ndarray, np.ndarray],
             weak: CellCandidates, image_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``found`` (ids, pixels, scores) and the corners of the verified ``view`` that no confident candidate
    took, each taking the weak candidate the view gives it (`assign_ids`: the mutual nearest within reach of the
    view's own prediction) where that lies within `WEAK_REACH_PX` of where its found neighbours put it (a homography
    fitted to the found corners within `LOCAL_SQUARES` squares of it on the board: a lens bends the board away from
    the view's one homography); strongest first. The markers name the corner: the point head need only say that
    one is there. Both must agree: four neighbours fit a homography exactly, whatever their error, and in a
    motion-blurred frame such a fit put a corner a square from its place, onto another weak candidate there."""
    ids, pixels, scores = found
    if len(ids) < 4:
        return found
    own_ids, own_pixels, own_scores = assign_ids(view, board_xy, weak, image_size)
    missing = ~np.isin(own_ids, ids)
    own_ids, own_pixels, own_scores = own_ids[missing], own_pixels[missing], own_scores[missing]
    placed, places = _agreed_places(board_xy, own_ids, ids, pixels)
    own_ids, own_pixels, own_scores = own_ids[placed], own_pixels[placed], own_scores[placed]
    agree = lengths(own_pixels.astype(np.float64) - places) <= WEAK_REACH_PX
    if not agree.any():
        return found
    ids = np.concatenate([ids, own_ids[agree]])
    pixels = np.concatenate([pixels, own_pixels[agree]]).astype(np.float32)
    scores = np.concatenate([scores, own_scores[agree]]).astype(np.float32)
    order = np.argsort(-scores, kind="stable")
    return ids[order], pixels[order], scores[order]


def _agreed_places(board_xy: np.ndarray, targets: np.ndarray, ids: np.ndarray, pixels: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Where the found corners (``ids`` (N,) at ``pixels`` (N, 2)) put each of ``targets`` (T,): a homography fitted
    to those within `LOCAL_SQUARES` squares of it on the board (`local_predictions`; a lens bends the board away
    from the view's one homography). -> ((T,) bool: the targets with a fit that all its corners meet within
    `LOCAL_FIT_PX`, their places (K, 2) float64 pixels in the targets' order); where the neighbours disagree, no
    place."""
    offsets, weight, slots = _neighbourhoods(board_xy, targets, ids)
    fittable = _fittable(offsets, weight)
    if not fittable.any():
        return fittable, np.zeros((0, 2))
    places, misfit = local_predictions(offsets[fittable], weight[fittable], pixels.astype(np.float64)[slots[fittable]])
    agree = np.all(misfit <= LOCAL_FIT_PX, axis=1)
    agreed = fittable.copy()
    agreed[fittable] = agree
    return agreed, places[agree]


def _fill_in_by_pattern(gray: np.ndarray, board: BoardSpec, view: BoardView, board_xy: np.ndarray,
                        found: tuple[np.ndarray, np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``found`` (ids, pixels, scores) and the corners of the verified ``view`` in ``gray`` that no candidate took,
    where their found neighbours agree on a place (as `_fill_in`) and the board's printed pattern lies around it,
    a cast shadow's edge allowed (`junction.pattern_evidence` >= `PATTERN_MIN_T`): the point head loses corners
    under a shadow's edge. Each takes the pixel nearest that place and score 0 (no point head evidence)."""
    ids, pixels, scores = found
    if len(ids) < 4:
        return found
    height, width = gray.shape
    predicted, w = apply_homography(view.homography, board_xy)
    in_view = (w > 0) & np.all(predicted >= 0, axis=1) & (predicted[:, 0] <= width - 1) \
        & (predicted[:, 1] <= height - 1)
    targets = np.flatnonzero(in_view & ~np.isin(np.arange(len(board_xy)), ids))
    agreed, places = _agreed_places(board_xy, targets, ids, pixels)
    targets = targets[agreed]
    if len(targets) == 0:
        return found
    # A lens bends a board's edge away from a fit carried past its corners, onto the next corner along a diagonal:
    # the pattern there fits as well (the same checker), so no corner is put where another was found.
    apart = pairwise_distances(places, pixels.astype(np.float64)).min(axis=1) >= PATTERN_APART * corner_spacing(pixels)
    targets, places = targets[apart], places[apart]
    evidence = pattern_evidence(gray, board, view.homography, targets, places)
    shown = evidence >= PATTERN_MIN_T
    if not shown.any():
        return found
    new_pixels = np.rint(places[shown]).astype(np.float32)
    return (np.concatenate([ids, targets[shown]]), np.concatenate([pixels.astype(np.float32), new_pixels]),
            np.concatenate([scores, np.full(int(shown.sum()), PATTERN_SCORE, np.float32)]).astype(np.float32))
