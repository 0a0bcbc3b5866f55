"""Whether the markers a view of the board puts in the image are there (`placement` and the detector's last
check): each square the view predicts is read, and the view stands when enough markers agree with the board's
layout, beyond chance (`view_is_verified`, `marker_view_verified`: agreement, rank against the other codes, the
chance tail), and not too many read as other codes of the dictionary than the layout prints there
(`layout_contradicted`: a board file of another layout with the same IDs), and none of its markers are printed
beyond the edge the view puts the board's at (`layout_ends_short`: a board file with shifted IDs). Board units are
metres; pixels OpenCV's.
"""

from __future__ import annotations

import math
from functools import cache

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.detection.markers.marker_reader import (DEFAULT_READER, BoardMarkers, board_markers, correlate,
                                                     read_squares)


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


def square_translations(offsets: np.ndarray) -> np.ndarray:
    """(N, 2) offsets (x, y) -> (N, 3, 3) homogeneous translations by each."""
    moves = np.zeros((len(offsets), 3, 3))
    moves[:, [0, 1, 2], [0, 1, 2]] = 1.0
    moves[:, :2, 2] = offsets
    return moves


def reading_image(gray: np.ndarray, read_gray: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(the image to read markers in, 3x3 map from ``gray``'s pixels to its pixels; centres to centres)."""
    if read_gray is None or read_gray.shape == gray.shape:
        return gray, np.eye(3)
    rx, ry = read_gray.shape[1] / gray.shape[1], read_gray.shape[0] / gray.shape[0]
    return read_gray, np.array([[rx, 0, 0.5 * rx - 0.5], [0, ry, 0.5 * ry - 0.5], [0, 0, 1]])


def _read_markers(gray: np.ndarray, board: BoardSpec, homography: np.ndarray, reader: str | None
                  ) -> tuple[BoardMarkers, np.ndarray, np.ndarray]:
    """Read every marker square of ``board`` that ``homography`` (board metres -> pixels) puts wholly in ``gray``.
    -> (`board_markers`, every square's read bits (`read_squares`), the readable squares' indices (R,))."""
    markers = board_markers(board)
    scale = np.diag([board.square_length, board.square_length, 1.0])
    squares = homography @ scale @ square_translations(markers.squares)  # (M, 3, 3): each marker's square frame -> pixels
    bits, contrast = read_squares(gray, squares, markers.size, markers.ratio, reader)
    return markers, bits, np.flatnonzero(contrast > 0)


def _expected_ranks(gray: np.ndarray, board: BoardSpec, homography: np.ndarray, reader: str | None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read every marker square of ``board`` that ``homography`` (board metres -> pixels) puts wholly in ``gray``.
    -> (readable markers' indices (R,) into `board_markers`, whether each read correlates best with the marker
    printed there in the right turn (R,) bool, the rank of that (marker, turn) among all the board's (R,) in [0, 1]:
    the fraction of the other (marker, turn) pairs that correlate less, ties counted half)."""
    return _ranks_of(*_read_markers(gray, board, homography, reader), reader)


def _ranks_of(markers: BoardMarkers, bits: np.ndarray, readable: np.ndarray, reader: str | None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`_expected_ranks` of reads made (`_read_markers`' three results)."""
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


def binomial_tail(n: int, k: int, p: float) -> float:
    """P(X >= k) for X ~ Binomial(n, p): the chance rules' common tail."""
    return float(sum(math.comb(n, i) * p ** i * (1 - p) ** (n - i) for i in range(k, n + 1)))


def code_match_chance(codes: int, board: BoardSpec) -> float:
    """Chance that a square showing none of ``codes`` codes of ``board``'s dictionary reads within `code_error_limit`
    bits of one of them: codes x sum_{j <= limit} C(n, j) / 2^n (n inner bits), at most 1."""
    size = board.cv_dictionary().markerSize ** 2
    return min(1.0, codes * sum(math.comb(size, j) for j in range(code_error_limit(board) + 1)) / 2.0 ** size)


def chance_of_agreement(agreeing: int, readable: int, markers: int) -> float:
    """Probability that ``agreeing`` or more of ``readable`` squares that show no marker of the board would
    each read best as the marker the view expects there, by chance: 1 in 4 x ``markers`` each (binomial tail)."""
    p = 1.0 / (4 * markers)
    return binomial_tail(readable, agreeing, p)


def view_is_verified(gray: np.ndarray, board: BoardSpec, homography: np.ndarray, reader: str | None = None,
                     chosen_by: np.ndarray | None = None) -> bool:
    """True when the markers in the view ``homography`` (board metres -> pixels) of canonical ``gray`` read as
    the board's own: at least `MIN_MARKERS` read best as themselves, and either at least `MIN_MARKER_AGREEMENT`
    of the readable ones do and more than chance could explain (`chance_of_agreement` <= `MAX_CHANCE`), or
    the readable markers other than ``chosen_by`` (the marker IDs whose reads chose the view) rank their own
    marker above chance by `MIN_RANK_Z` standard errors (`rank_z`), or their codes do (`code_chance`); and the
    markers do not contradict the board's layout (`layout_contradicted`: checked last, on the views that pass, as
    most views tried fail before)."""
    reads = _read_markers(gray, board, homography, reader)  # once: every rule below reads the same squares
    readable, best, ranks = _ranks_of(*reads, reader)
    agreeing = int(best.sum())
    if agreeing < MIN_MARKERS:
        return False
    markers = reads[0]
    unbiased = ~np.isin(markers.ids[readable], np.asarray([] if chosen_by is None else chosen_by))
    verified = (agreeing >= MIN_MARKER_AGREEMENT * len(readable)
                and chance_of_agreement(agreeing, len(readable), board.num_markers) <= MAX_CHANCE) \
        or rank_z(ranks[unbiased]) >= MIN_RANK_Z \
        or code_chance(_code_errors_of(*reads, reader), markers.size ** 2, code_error_limit(board)) <= MAX_CHANCE
    return verified and not layout_contradicted(agreeing, len(readable), _contradicting_of(*reads, reader, board),
                                                board)


def contradicting_markers(gray: np.ndarray, board: BoardSpec, homography: np.ndarray, reader: str | None = None
                          ) -> int:
    """Marker squares of ``board`` that ``homography`` (board metres -> pixels) puts wholly and readably in canonical
    ``gray`` and whose code reads, within `code_error_limit` bits, as a marker of the board's dictionary other than
    the one its layout prints there (another ID, or that one turned). Each is a marker where this layout puts
    another: a board file of another layout (transposed, other or shifted IDs) whose markers happen to fit a
    view. A right layout has none: two codes of one dictionary (any turns) differ in more than twice the bits the
    limit allows, and a square that reads as no code (blur, glare, dark) contradicts nothing."""
    return _contradicting_of(*_read_markers(gray, board, homography, reader), reader, board)


def _contradicting_of(markers: BoardMarkers, bits: np.ndarray, readable: np.ndarray, reader: str | None,
                      board: BoardSpec) -> int:
    """`contradicting_markers` of reads made (`_read_markers`' three results)."""
    if len(readable) == 0:
        return 0
    white = _thresholded(bits[readable], reader)  # (R, n * n)
    limit = code_error_limit(board)
    printed = np.sum(white != markers.bits[readable, 0].reshape(len(readable), -1), axis=1) <= limit
    if printed.all():
        return 0
    # Every code of the dictionary in every turn, as bit words: XOR and a popcount (~7x faster than comparing bits).
    errors = _popcount(_code_words(white[~printed])[:, None] ^ dictionary_words(board.dictionary)[None, :])
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
    p = code_match_chance(len(dictionary_codes(board.dictionary)), board)
    n = readable - agreeing
    tail = binomial_tail(n, contradicting, p)
    return tail <= MAX_CHANCE



# The squares around a board that a view's lattice is continued to, on each side: a board file whose IDs are shifted
# by one marker (two squares along a row) or by a row leaves printed markers there.
BEYOND_SQUARES = 2


def markers_beyond(gray: np.ndarray, board: BoardSpec, homography: np.ndarray, reader: str | None = None
                   ) -> tuple[int, int]:
    """Read the squares of the board's lattice continued `BEYOND_SQUARES` squares past each edge that ``homography``
    (board metres -> pixels) puts wholly and readably in canonical ``gray`` (the whole frame: a search region's crop
    may cut them off). -> (readable squares, those whose code reads as one of the board's own markers, within
    `code_error_limit` bits, in the orientation the board's own markers have in the view).

    A right layout has paper margin or background there, which reads as no marker of the board. A board file whose
    IDs are shifted (or a larger board file with the print's IDs) fits the markers it covers, and every marker in
    that view agrees with it; the printed markers it leaves out are then seen beyond its edge, each a marker of this
    board where its layout has none: evidence from the print itself, which darkness or occlusion can hide but not
    fake."""
    columns = np.arange(-BEYOND_SQUARES, board.squares_x + BEYOND_SQUARES)
    rows = np.arange(-BEYOND_SQUARES, board.squares_y + BEYOND_SQUARES)
    grid = np.stack(np.meshgrid(columns, rows), axis=-1).reshape(-1, 2)
    outside = grid[(grid[:, 0] < 0) | (grid[:, 0] >= board.squares_x) | (grid[:, 1] < 0)
                   | (grid[:, 1] >= board.squares_y)]
    markers = board_markers(board)
    scale = np.diag([board.square_length, board.square_length, 1.0])
    bits, contrast = read_squares(gray, homography @ scale @ square_translations(outside), markers.size,
                                  markers.ratio, reader)
    readable = np.flatnonzero(contrast > 0)
    if len(readable) == 0:
        return 0, 0
    white = _thresholded(bits[readable], reader)  # (R, n * n)
    own = markers.bits[:, 0].reshape(len(markers.ids), -1)  # (M, n * n), in the board's own frame
    errors = np.sum(white[:, None, :] != own[None, :, :], axis=2)
    return len(readable), int(np.sum(errors.min(axis=1) <= code_error_limit(board)))


def markers_beyond_contradict(readable: int, found: int, board: BoardSpec) -> bool:
    """Whether ``found`` of the ``readable`` squares beyond the board's edge (`markers_beyond`) reading as its own
    markers is more than chance explains (binomial tail at most `MAX_CHANCE`): a square that shows no marker of the
    board reads within `code_error_limit` bits of one of its M codes, in one orientation, with chance
    M x sum_{j <= limit} C(n, j) / 2^n (n inner bits)."""
    if found == 0:
        return False
    tail = binomial_tail(readable, found, code_match_chance(board.num_markers, board))
    return tail <= MAX_CHANCE


def layout_ends_short(gray: np.ndarray, board: BoardSpec, homography: np.ndarray, reader: str | None = None) -> bool:
    """True when the board's own markers are printed beyond the edge of the view ``homography`` (board metres ->
    canonical ``gray``'s pixels, the whole frame) puts the board at (`markers_beyond`, `markers_beyond_contradict`):
    the board file's layout is not the print's."""
    return markers_beyond_contradict(*markers_beyond(gray, board, homography, reader), board)

@cache
def dictionary_codes(dictionary: str) -> np.ndarray:
    """(D * 4, n * n) bool: every marker code of the OpenCV dictionary ``dictionary`` in each of its quarter turns,
    bits row by row as `marker_reader.board_markers` reads them (white True)."""
    cv_dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    size = cv_dictionary.markerSize
    # Unpacked for all markers at once (`Dictionary.getBitsFromByteList`, one marker a call, took 60-70 ms for a
    # 1,000-marker dictionary, on the first verified view of a run); the same bits for every OpenCV dictionary.
    full, rest = divmod(size * size, 8)
    packed = cv_dictionary.bytesList.reshape(len(cv_dictionary.bytesList), -1)[:, :full + (rest > 0)]  # turn 0's bytes
    bits = np.unpackbits(packed, axis=1)
    if rest:  # the last byte holds its bits at its low end
        bits = np.concatenate([bits[:, :8 * full], bits[:, 8 * full + 8 - rest:]], axis=1)
    bits = bits.reshape(-1, size, size) > 0
    return np.stack([np.rot90(bits, turn, axes=(1, 2)) for turn in range(4)], axis=1).reshape(-1, size * size)


@cache
def dictionary_words(dictionary: str) -> np.ndarray:
    """(D * 4,) uint64: `dictionary_codes` as bit words (`_code_words`)."""
    return _code_words(dictionary_codes(dictionary))


def _code_words(bits: np.ndarray) -> np.ndarray:
    """(R, b) bool, b <= 64 -> (R,) uint64: bit i of each word is column i."""
    weights = np.uint64(1) << np.arange(bits.shape[1], dtype=np.uint64)
    return (bits.astype(np.uint64) * weights).sum(axis=1, dtype=np.uint64)


_M1, _M2, _M4, _H01 = (np.uint64(v) for v in (0x5555555555555555, 0x3333333333333333, 0x0F0F0F0F0F0F0F0F,
                                                0x0101010101010101))


def _popcount(words: np.ndarray) -> np.ndarray:
    """uint64 array -> the set bits of each, as uint64 (the SWAR count; numpy < 2 has no `bitwise_count`)."""
    x = words - ((words >> np.uint64(1)) & _M1)
    x = (x & _M2) + ((x >> np.uint64(2)) & _M2)
    x = (x + (x >> np.uint64(4))) & _M4
    return (x * _H01) >> np.uint64(56)  # the byte sums gathered in the top byte (the product wraps, as meant)


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
    return _code_errors_of(*_read_markers(gray, board, homography, reader), reader)


def _code_errors_of(markers: BoardMarkers, bits: np.ndarray, readable: np.ndarray, reader: str | None) -> np.ndarray:
    """`code_errors` of reads made (`_read_markers`' three results)."""
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
    read_gray, to_read = reading_image(gray, read_gray)
    return view_is_verified(read_gray, board, to_read @ homography, reader, chosen_by)
