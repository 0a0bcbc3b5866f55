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

import math
from dataclasses import dataclass
from functools import cache

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.core.detection import corner_spacing, no_corners
from deepcharuco.core.vectors import lengths, pairwise_distances
from deepcharuco.detection.board_check import BoardView, apply_homography, assign_ids, in_image
from deepcharuco.detection.junction import pattern_evidence
from deepcharuco.detection.lattice import cell_homographies, find_cells, quad_areas, squarest_cells
from deepcharuco.detection.marker_reader import (DEFAULT_READER, QUARTER_TURNS, board_markers, correlate, match_markers,
                                                 read_squares)
from deepcharuco.networks.cells import CellCandidates

# Two distinct markers in agreement: one read can be a fluke (4x4 markers have 16 bits), two that also
# agree on where the board is are not.
MIN_MARKERS = 2
# The final view's own check: of the board's markers it puts wholly in the image and can read, this
# fraction must read best as the marker printed there (a look-alike board reads as chance, 1 / markers).
# 0.5 refused blurred views of boards with many small markers that the chance bound below already proves
# (an 11x8 board at blur k = 10: 14 of 44 read as themselves, chance ~1e-20; the view was right). Chosen on
# the validation views of train/bit_reader.py (5 boards, not the report's): blur k = 10 0.859 at 0.5 and
# 0.35, 0.892 at 0.25, 0.15 and 0; the largest on the plateau is kept. Look-alikes (10 views each of the
# paper's and the three unseen boards' look-alikes) still give no pose and no corner.
MIN_MARKER_AGREEMENT = 0.25
# ... and more than chance explains. The view is the best of up to HYPOTHESES tried, on squares it picked
# itself: 2 of 3 markers agreeing on a board of 12 happens by chance in photos (1 of 25 scikit-image photos
# gave 4 corners); 1e-5 asks 3 of 3 there, 2 of 3 on a board of 200 markers.
MAX_CHANCE = 1e-5
# ... or, where blur leaves few markers reading best as themselves, the markers' ranks tell: each readable square's
# expected marker ranks among all the board's markers and turns by its correlation with the read (0 worst, 1 best);
# squares that show no marker of the board rank uniformly (mean 0.5, variance 1/12 each), so the mean rank over n
# squares is z = (mean - 0.5) / sqrt(1 / (12 n)) standard errors above chance. The squares whose reads chose the
# view are left out (they were picked for agreeing). MIN_RANK_Z = 5 (chance ~3e-7): on validation renders (12x9
# DICT_4X4_1000 at blur k = 10, not the report's boards) right views scored 6.4-10.6, wrong ones 0.4 and -1.9;
# look-alikes of 6 boards (other dictionaries and IDs, mirrored, plain; 10 views each, at their true pose and at
# the view the search found) at most 2.4.
MIN_RANK_Z = 5.0
# ... or, where neither rule proves the view, as on a board of too few markers to prove itself against its own (a
# 3x3 board has 4: even 4 of 4 reading best as themselves happens by chance with 1.5e-5, above MAX_CHANCE), each
# marker's bits tell:
# a square that shows none of the board's markers reads within e bits of the code expected there with chance
# sum_{j <= e} C(n, j) / 2^n (n inner bits). MIN_MARKERS markers within `code_error_limit` bits each, at least
# MIN_CODE_SHARE of the readable ones, whose chances multiply to MAX_CHANCE or less, verify the view (two 5x5 markers
# two bits off each: 9e-11). The share keeps out look-alikes whose codes match by symmetry: a mirrored 12x9
# DICT_4X4_1000 board reads 2 of its 54 markers exactly as the codes expected there. The limit is at most
# the dictionary's own correction capacity (OpenCV's maxCorrectionBits: half its least distance between codes, so a
# marker of another board of the dictionary reads within it only with more bit errors than that) and one bit per 12
# (a 4x4 code: 1; 5x5: 2; 6x6: 3): a view fitted to a coarse level's four corners samples the bits up to half a
# bit off, and on 8 validation frames drawn as `benchmarks/detect.py`'s 5 MP row (rng seed 0) right views read 0-2
# bits off.
BITS_PER_ERROR = 12
MIN_CODE_SHARE = 0.5
# A video's board where the frame before put it (`view_near`): the view is moved by the median offset of the corners
# that have a candidate within NEAR_FRACTION of the corner spacing, at least MIN_NEAR of them (a board that moved
# farther is found by the search through the cells, as in any frame).
NEAR_FRACTION = 0.4
MIN_NEAR = 4
# ... and stands when it names NEAR_SHARE of the corners it puts in the image; else the cells are searched too, and the
# view naming more corners kept (a blurred board's view moved by the median offset may claim only some of them).
NEAR_SHARE = 0.9
# Corners the verified view predicts where no candidate reaches the detector's threshold may take a weaker one
# (point confidence >= WEAK_CONFIDENCE, within WEAK_REACH_PX of the prediction): the markers already name the
# corner, the point head need only say that one is there.
WEAK_CONFIDENCE = 0.05
WEAK_REACH_PX = 3.0
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
SEARCH_CANDIDATES = 300  # corners the view is searched among, most confident first: bounds the time on noise
MAX_CELLS = 600  # cells read at most (300 corners frame about 300 cells)
HYPOTHESES = 256  # proposals tried as the board's view, best correlated first
AGREEMENT = 0.3  # two markers agree when one's view puts the other's square within this many square sides
# A cell's edge neighbours: the markers of a ChArUco board sit in the squares next to the black ones.
NEIGHBOUR_OFFSETS = np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]], np.float64)


@dataclass(frozen=True)
class MarkerView:
    """A board view backed by markers: ``view`` (homography board metres -> pixels), ``marker_ids``
    (distinct marker IDs that back it) and ``reads`` (how many square reads matched those markers)."""

    view: BoardView
    marker_ids: np.ndarray
    reads: int


def _translations(offsets: np.ndarray) -> np.ndarray:
    """(N, 2) offsets (x, y) -> (N, 3, 3) homogeneous translations by each."""
    moves = np.zeros((len(offsets), 3, 3))
    moves[:, [0, 1, 2], [0, 1, 2]] = 1.0
    moves[:, :2, 2] = offsets
    return moves


class CellReads:
    """The marker reads of each cell's five squares (the cell and its edge neighbours, `NEIGHBOUR_OFFSETS`), kept by
    cell: `corners_from_markers`' second pass through the cells (every one) reads only those its first (the squarest)
    did not. A square's read depends on its cell's corners alone, so a kept read is the read it would make again.
    For one image, one reader and one set of candidate ``pixels``."""

    def __init__(self):
        self.keys = np.zeros(0, np.int64)  # sorted cell keys (`_cell_keys`)
        self.bits: np.ndarray | None = None  # (K, 5, n, n) float32, in the keys' order
        self.contrast = np.zeros((0, len(NEIGHBOUR_OFFSETS)), np.float32)

    def read(self, quads: np.ndarray, count: int, read: callable) -> tuple[np.ndarray, np.ndarray]:
        """(Q, 4) cells among ``count`` candidates -> (bits (Q * 5, n, n), contrast (Q * 5,)) as `read_squares` gives
        them, rows cell by cell; ``read(rows)`` reads the squares of the cells ``rows`` (Q,) bool not kept yet."""
        keys = _cell_keys(quads, count)
        at = np.searchsorted(self.keys, keys).clip(max=max(len(self.keys) - 1, 0))
        kept = (self.keys[at] == keys) if len(self.keys) else np.zeros(len(keys), bool)
        new_bits, new_contrast = read(~kept)
        side = len(NEIGHBOUR_OFFSETS)
        new_bits = new_bits.reshape(-1, side, *new_bits.shape[1:])
        new_contrast = new_contrast.reshape(-1, side)
        if self.bits is None:
            self.bits = np.zeros((0, *new_bits.shape[1:]), np.float32)
        bits = np.empty((len(keys), *new_bits.shape[1:]), np.float32)
        contrast = np.empty((len(keys), side), np.float32)
        bits[kept], contrast[kept] = self.bits[at[kept]], self.contrast[at[kept]]
        bits[~kept], contrast[~kept] = new_bits, new_contrast
        order = np.argsort(np.concatenate([self.keys, keys[~kept]]), kind="stable")
        self.keys = np.concatenate([self.keys, keys[~kept]])[order]
        self.bits = np.concatenate([self.bits, new_bits])[order]
        self.contrast = np.concatenate([self.contrast, new_contrast])[order]
        return bits.reshape(-1, *bits.shape[2:]), contrast.reshape(-1)


def _cell_keys(quads: np.ndarray, count: int) -> np.ndarray:
    """(Q, 4) cells (ordered corners a, b, d, c among ``count`` candidates) -> (Q,) int64 one key each."""
    quads = np.asarray(quads, np.int64)
    if count ** 4 >= 2 ** 63:
        raise ValueError(f"{count} candidates: too many for int64 cell keys")
    return ((quads[:, 0] * count + quads[:, 1]) * count + quads[:, 2]) * count + quads[:, 3]


def find_marker_view(gray: np.ndarray, board: BoardSpec, pixels: np.ndarray, quads: np.ndarray,
                     read_gray: np.ndarray | None = None, reader: str | None = None, reads: CellReads | None = None
                     ) -> MarkerView | None:
    """The view of ``board`` that the markers in the cells ``quads`` (Q, 4) (`lattice.find_cells`) between
    ``pixels`` (N, 2) corner candidates agree on, or None.

    ``gray``: (H, W) uint8 in the board's canonical appearance (`print_face.canonical_view`), the image
    ``pixels`` (most confident first) were found in; ``read_gray``: the same image at a higher resolution to read the markers in
    (default ``gray``); ``reader``: `marker_reader.READERS` (default theirs); ``reads``: reads of cells made before in
    the same image by the same reader among the same ``pixels``, reused and added to. The view returned maps to
    ``gray``'s pixels."""
    if len(quads) == 0:
        return None
    if len(quads) > MAX_CELLS:  # pixels come most confident first: keep the cells of the most confident corners
        quads = quads[np.argsort(quads.max(axis=1), kind="stable")[:MAX_CELLS]]
    cells = cell_homographies(pixels, quads)  # (Q, 3, 3) unit square -> image
    # Every cell and its edge neighbours: (Q * 5) squares, each with its own unit frame.
    shifts = _translations(NEIGHBOUR_OFFSETS)
    # The same square is read from up to five cells: each read is one more vote, and a square badly
    # extrapolated from one cell is read well from another.
    squares = np.einsum("qij,sjk->qsik", cells, shifts).reshape(-1, 3, 3)
    markers = board_markers(board)
    read_gray, to_read = _reading_image(gray, read_gray)
    if reads is None:
        bits, contrast = read_squares(read_gray, to_read @ squares, markers.size, markers.ratio, reader)
    else:
        by_cell = squares.reshape(len(quads), len(NEIGHBOUR_OFFSETS), 3, 3)
        bits, contrast = reads.read(quads, len(pixels), lambda rows: read_squares(
            read_gray, to_read @ by_cell[rows].reshape(-1, 3, 3), markers.size, markers.ratio, reader))
    matches = match_markers(bits, contrast, markers, reader=reader)
    if len(np.unique(matches.marker)) < MIN_MARKERS:
        return None
    # Each proposal: board square units -> image, via its square's frame and the quarter turn.
    square_xy = markers.squares[matches.marker].astype(np.float64)
    proposals = squares[matches.read] @ QUARTER_TURNS[matches.turn] @ _translations(-square_xy)
    # Proposal i agrees with proposal j when it puts j's square where j was read, the same way round:
    # compare the square's centre and its first corner. Only the best-correlated proposals are tried
    # as the view (the right view has many proposals, so some among the best): O(HYPOTHESES x K).
    hypotheses = np.argsort(-matches.ncc, kind="stable")[:HYPOTHESES]
    reach = AGREEMENT * _square_sides(squares[matches.read])  # (K,)
    # A far-off proposal may send a point to infinity. The centres first, for every (hypothesis, proposal) pair:
    # (H, K); the first corners then only for the pairs whose centres agree (0.3-5 % of them on the report's boards).
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        centres = np.c_[square_xy + 0.5, np.ones(len(square_xy))]
        # (H, 3, K): one matrix product for all hypotheses (a stacked matmul of H 3x3s is 2x slower, same numbers).
        mapped = (proposals[hypotheses].reshape(-1, 3) @ centres.T).reshape(len(hypotheses), 3, -1)
        agrees = _lands_within(mapped, _apply_each(proposals, centres[:, :2]), reach)
        pair_h, pair_k = np.nonzero(agrees)
        firsts = np.c_[square_xy, np.ones(len(square_xy))]
        mapped = np.einsum("nij,nj->ni", proposals[hypotheses[pair_h]], firsts[pair_k])[:, :, None]  # (n, 3, 1)
        observed = _apply_each(proposals, square_xy)[pair_k][:, None]  # (n, 1, 2)
        agrees[pair_h, pair_k] = _lands_within(mapped, observed, reach[pair_k][:, None])[:, 0]
    support = _support(matches.marker, matches.ncc, agrees)
    best = int(np.argmax(support))
    if len(np.unique(matches.marker[agrees[best]])) < MIN_MARKERS:
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


def _reading_image(gray: np.ndarray, read_gray: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(the image to read markers in, 3x3 map from ``gray``'s pixels to its pixels; centres to centres)."""
    if read_gray is None or read_gray.shape == gray.shape:
        return gray, np.eye(3)
    rx, ry = read_gray.shape[1] / gray.shape[1], read_gray.shape[0] / gray.shape[0]
    return read_gray, np.array([[rx, 0, 0.5 * rx - 0.5], [0, ry, 0.5 * ry - 0.5], [0, 0, 1]])


def _expected_ranks(gray: np.ndarray, board: BoardSpec, homography: np.ndarray, reader: str | None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read every marker square of ``board`` that ``homography`` (board metres -> pixels) puts wholly in ``gray``.
    -> (readable markers' indices (R,) into `board_markers`, whether each read correlates best with the marker
    printed there in the right turn (R,) bool, the rank of that (marker, turn) among all the board's (R,) in [0, 1]:
    the fraction of the other (marker, turn) pairs that correlate less, ties counted half)."""
    markers = board_markers(board)
    scale = np.diag([board.square_length, board.square_length, 1.0])
    squares = homography @ scale @ _translations(markers.squares)  # (M, 3, 3): each marker's square frame -> pixels
    bits, contrast = read_squares(gray, squares, markers.size, markers.ratio, reader)
    readable = np.flatnonzero(contrast > 0)
    if len(readable) == 0:
        return readable, np.zeros(0, bool), np.zeros(0)
    ncc = correlate(bits[readable], markers, reader).reshape(len(readable), len(markers.ids) * 4)
    expected = ncc[np.arange(len(readable)), readable * 4][:, None]
    below = np.sum(ncc < expected, axis=1) + 0.5 * (np.sum(ncc == expected, axis=1) - 1)
    return readable, ncc.argmax(axis=1) == readable * 4, below / max(ncc.shape[1] - 1, 1)


def marker_agreement(gray: np.ndarray, board: BoardSpec, homography: np.ndarray, reader: str | None = None
                     ) -> tuple[int, int]:
    """Read every marker square of ``board`` that ``homography`` (board metres -> pixels) puts wholly in
    ``gray`` (canonical appearance). -> (markers whose read correlates best with the marker printed there,
    in the right turn, among all the board's markers and turns; readable markers)."""
    readable, best, _ = _expected_ranks(gray, board, homography, reader)
    return int(best.sum()), len(readable)


def rank_z(ranks: np.ndarray) -> float:
    """Standard errors by which the mean of ``ranks`` (`_expected_ranks`) exceeds chance (0.5; 0.0 for none)."""
    return float((np.mean(ranks) - 0.5) * np.sqrt(12 * len(ranks))) if len(ranks) else 0.0


def chance_of_agreement(agreeing: int, readable: int, markers: int) -> float:
    """Probability that ``agreeing`` or more of ``readable`` squares that show no marker of the board would
    each read best as the marker the view expects there, by chance: 1 in 4 x ``markers`` each (binomial tail)."""
    p = 1.0 / (4 * markers)
    return float(sum(math.comb(readable, k) * p ** k * (1 - p) ** (readable - k) for k in range(agreeing, readable + 1)))


def view_is_verified(gray: np.ndarray, board: BoardSpec, homography: np.ndarray, reader: str | None = None,
                     chosen_by: np.ndarray | None = None) -> bool:
    """True when the markers in the view ``homography`` (board metres -> pixels) of canonical ``gray`` read as
    the board's own: at least `MIN_MARKERS` read best as themselves, and either at least `MIN_MARKER_AGREEMENT`
    of the readable ones do and more than chance could explain (`chance_of_agreement` <= `MAX_CHANCE`), or
    the readable markers other than ``chosen_by`` (the marker IDs whose reads chose the view) rank their own
    marker above chance by `MIN_RANK_Z` standard errors (`rank_z`), or their codes do (`code_chance`); and the
    markers do not contradict the board's layout (`layout_contradicted`: checked last, on the views that pass, as
    most views tried fail before)."""
    readable, best, ranks = _expected_ranks(gray, board, homography, reader)
    agreeing = int(best.sum())
    if agreeing < MIN_MARKERS:
        return False
    markers = board_markers(board)
    unbiased = ~np.isin(markers.ids[readable], np.asarray([] if chosen_by is None else chosen_by))
    verified = (agreeing >= MIN_MARKER_AGREEMENT * len(readable)
                and chance_of_agreement(agreeing, len(readable), board.num_markers) <= MAX_CHANCE) \
        or rank_z(ranks[unbiased]) >= MIN_RANK_Z \
        or code_chance(code_errors(gray, board, homography, reader), markers.size ** 2,
                       code_error_limit(board)) <= MAX_CHANCE
    return verified and not layout_contradicted(agreeing, len(readable),
                                                contradicting_markers(gray, board, homography, reader), board)


def contradicting_markers(gray: np.ndarray, board: BoardSpec, homography: np.ndarray, reader: str | None = None
                          ) -> int:
    """Marker squares of ``board`` that ``homography`` (board metres -> pixels) puts wholly and readably in canonical
    ``gray`` and whose code reads, within `code_error_limit` bits, as a marker of the board's dictionary other than
    the one its layout prints there (another ID, or that one turned). Each is a marker where this layout puts
    another: a board file of another layout (transposed, other or shifted IDs) whose markers happen to fit a
    view. A right layout has none: two codes of one dictionary (any turns) differ in more than twice the bits the
    limit allows, and a square that reads as no code (blur, glare, dark) contradicts nothing."""
    markers = board_markers(board)
    scale = np.diag([board.square_length, board.square_length, 1.0])
    squares = homography @ scale @ _translations(markers.squares)
    bits, contrast = read_squares(gray, squares, markers.size, markers.ratio, reader)
    readable = np.flatnonzero(contrast > 0)
    if len(readable) == 0:
        return 0
    white = _thresholded(bits[readable], reader)  # (R, n * n)
    limit = code_error_limit(board)
    printed = np.sum(white != markers.bits[readable, 0].reshape(len(readable), -1), axis=1) <= limit
    codes = dictionary_codes(board.dictionary)  # (D * 4, n * n)
    errors = np.sum(white[~printed, None, :] != codes[None, :, :], axis=2) if (~printed).any() else np.zeros((0, 1))
    return int(np.sum(errors.min(axis=1) <= limit))


def layout_contradicted(agreeing: int, readable: int, contradicting: int, board: BoardSpec) -> bool:
    """Whether ``contradicting`` markers (`contradicting_markers`) of ``readable`` refuse a view that ``agreeing``
    of them back: a third as many as the backing ones, or more than chance could explain among those that do not
    back it (a blurred square reads as some code of a large dictionary by chance: 6 % of all 16-bit patterns are
    DICT_4X4_1000 codes; at most `MAX_CHANCE`, binomial tail). On the real sets a right layout read at most 4
    against 44 backing it (calibtargets' defocused 22x22 board); a wrong one 1 against 3, 2 against 2-4, 10 against 3."""
    if contradicting == 0:
        return False
    if contradicting >= agreeing / 3:
        return True
    p = min(1.0, len(dictionary_codes(board.dictionary)) * sum(
        math.comb(board.cv_dictionary().markerSize ** 2, j) for j in range(code_error_limit(board) + 1))
        / 2.0 ** board.cv_dictionary().markerSize ** 2)
    n = readable - agreeing
    tail = sum(math.comb(n, k) * p ** k * (1 - p) ** (n - k) for k in range(contradicting, n + 1))
    return tail <= MAX_CHANCE


@cache
def dictionary_codes(dictionary: str) -> np.ndarray:
    """(D * 4, n * n) bool: every marker code of the OpenCV dictionary ``dictionary`` in each of its quarter turns,
    bits row by row as `marker_reader.board_markers` reads them (white True)."""
    cv_dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    size = cv_dictionary.markerSize
    codes = [np.rot90(cv2.aruco.Dictionary.getBitsFromByteList(cv_dictionary.bytesList[i:i + 1], size) > 0, turn)
             for i in range(len(cv_dictionary.bytesList)) for turn in range(4)]
    return np.array(codes).reshape(len(codes), size * size)


def _thresholded(bits: np.ndarray, reader: str | None) -> np.ndarray:
    """(R, n, n) reads -> (R, n * n) bool, white bits: sampled reads halfway between the read's darkest and
    brightest bit, learned ones by the logit's sign."""
    flat = bits.reshape(len(bits), -1)
    if (reader or DEFAULT_READER) == "learned":
        return flat > 0
    low, high = flat.min(axis=1, keepdims=True), flat.max(axis=1, keepdims=True)
    return flat > (low + high) / 2


def code_error_limit(board: BoardSpec) -> int:
    """The bit errors a marker's read may have and still count as its code (`view_is_verified`)."""
    dictionary = board.cv_dictionary()
    return int(min(dictionary.maxCorrectionBits, dictionary.markerSize ** 2 // BITS_PER_ERROR))


def code_errors(gray: np.ndarray, board: BoardSpec, homography: np.ndarray, reader: str | None = None) -> np.ndarray:
    """(R,) for each marker square of ``board`` that ``homography`` (board metres -> pixels) puts wholly and readably
    in canonical ``gray``: how many of its inner bits, read and thresholded (sampled reads: halfway between the read's
    darkest and brightest bit; learned: the logit's sign), differ from the code printed there."""
    markers = board_markers(board)
    scale = np.diag([board.square_length, board.square_length, 1.0])
    squares = homography @ scale @ _translations(markers.squares)
    bits, contrast = read_squares(gray, squares, markers.size, markers.ratio, reader)
    readable = np.flatnonzero(contrast > 0)
    if len(readable) == 0:
        return np.zeros(0, np.int64)
    white = _thresholded(bits[readable], reader)
    expected = markers.bits[readable, 0].reshape(len(readable), -1)
    return np.sum(white != expected, axis=1)


def code_chance(errors: np.ndarray, bits: int, max_errors: int) -> float:
    """Chance that squares showing no marker of the board read as close to the expected codes as the `code_errors`
    ``errors`` within ``max_errors`` do (the product of each one's sum_{j <= e} C(bits, j) / 2^bits); 1.0 when fewer
    than `MIN_MARKERS`, or than `MIN_CODE_SHARE` of them, are that close."""
    close = np.asarray(errors)[np.asarray(errors) <= max_errors]
    if len(close) < max(MIN_MARKERS, MIN_CODE_SHARE * len(errors)):
        return 1.0
    return float(np.prod([sum(math.comb(bits, j) for j in range(int(e) + 1)) / 2.0 ** bits for e in close]))


def marker_view_verified(gray: np.ndarray, board: BoardSpec, homography: np.ndarray,
                         read_gray: np.ndarray | None = None, reader: str | None = None,
                         chosen_by: np.ndarray | None = None) -> bool:
    """`view_is_verified` for a view found in ``gray`` (board metres -> ``gray``'s pixels), read in
    ``read_gray``, the same image at full resolution (default ``gray``)."""
    read_gray, to_read = _reading_image(gray, read_gray)
    return view_is_verified(read_gray, board, to_read @ homography, reader, chosen_by)


def _support(marker: np.ndarray, ncc: np.ndarray, agrees: np.ndarray) -> np.ndarray:
    """The evidence of each hypothesis' agreeing proposals: ``marker``, ``ncc`` (K,) per proposal, ``agrees``
    (H, K) bool -> (H,): each distinct marker counts once, by its best correlation (at least 0)."""
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
    """(R, 3, 3) unit-square frames -> (R,) square root of each square's area in the image (pixels)."""
    unit = np.array([[0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], np.float64)
    corners = unit @ np.transpose(squares, (0, 2, 1))  # (R, 4, 3)
    return np.sqrt(quad_areas(corners[:, :, :2] / corners[:, :, 2:]))


def _apply_each(homographies: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(K, 3, 3) homographies, (K, 2) points -> (K, 2): each point through its own homography."""
    mapped = np.einsum("kij,kj->ki", homographies, np.c_[xy, np.ones(len(xy))])
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
    candidate). Candidates below it (down to `WEAK_CONFIDENCE`, as the caller chose them) only fill in
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
    squarest = squarest_cells(strongest, every)
    reads = CellReads()  # the squarest cells' reads, reused when every cell is read
    for quads in (squarest, every) if len(squarest) < len(every) else (every,):
        found = find_marker_view(gray, board, strongest, quads, read_gray, reader, reads)
        verified = None if found is None else \
            _verified_corners(gray, board, board_xy, candidates, found, refits, read_gray, reader)
        if verified is not None:
            break
    else:
        return no_corners(), None
    return _filled_in(gray, board, board_xy, verified, weak, found)


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
    took, each taking the weak candidate nearest to where its found neighbours put it (a homography fitted to
    the found corners within `LOCAL_SQUARES` squares of it on the board: a lens bends the board away from the
    view's one homography) if that is within `WEAK_REACH_PX`, within `assign_ids`' reach of the view's own
    prediction, and no other corner's; strongest first. The markers name the corner: the point head need only
    say that one is there."""
    ids, pixels, scores = found
    if len(ids) < 4:
        return found
    candidates, confidence = weak.pixels.astype(np.float64), weak.confidence
    own_ids, _, _ = assign_ids(view, board_xy, weak, image_size)  # corners the view lets take a weak candidate
    targets, places = _agreed_places(board_xy, own_ids[~np.isin(own_ids, ids)], ids, pixels)
    extra: list[tuple[int, int]] = []
    for corner, place in zip(targets.tolist(), places):
        gap = lengths(candidates - place)
        best = int(np.argmin(gap))
        if gap[best] <= WEAK_REACH_PX:
            extra.append((corner, best))
    if not extra:
        return found
    chosen: dict[int, int] = {}
    for corner, candidate in extra:  # one candidate, one corner
        if candidate not in chosen.values():
            chosen[corner] = candidate
    new_ids = np.array(list(chosen), np.int64)
    cells = np.array(list(chosen.values()), np.int64)
    ids = np.concatenate([ids, new_ids])
    pixels = np.concatenate([pixels, weak.pixels[cells]]).astype(np.float32)
    scores = np.concatenate([scores, confidence[cells]]).astype(np.float32)
    order = np.argsort(-scores, kind="stable")
    return ids[order], pixels[order], scores[order]


def _agreed_places(board_xy: np.ndarray, targets: np.ndarray, ids: np.ndarray, pixels: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Where the found corners (``ids`` (N,) at ``pixels`` (N, 2)) put each of ``targets`` (T,): a homography fitted
    to those within `LOCAL_SQUARES` squares of it on the board (`local_predictions`; a lens bends the board away
    from the view's one homography). -> (the targets with a fit that all its corners meet within `LOCAL_FIT_PX`
    (K,), their places (K, 2) float64 pixels); where the neighbours disagree, no place."""
    offsets, weight, slots = _neighbourhoods(board_xy, targets, ids)
    fittable = _fittable(offsets, weight)
    if not fittable.any():
        return targets[:0], np.zeros((0, 2))
    places, misfit = local_predictions(offsets[fittable], weight[fittable], pixels.astype(np.float64)[slots[fittable]])
    agree = np.all(misfit <= LOCAL_FIT_PX, axis=1)
    return targets[fittable][agree], places[agree]


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
    targets, places = _agreed_places(board_xy, np.flatnonzero(in_view & ~np.isin(np.arange(len(board_xy)), ids)),
                                     ids, pixels)
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
