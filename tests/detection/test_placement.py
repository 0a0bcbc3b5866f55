"""The markers decoding (`deepcharuco.detection.markers.placement`): the final marker check's rank rule (blurred small markers that
rarely read best as themselves still rank their own marker high; look-alikes rank it at chance) and the weak point
candidates that fill in corners of a verified view."""

import cv2
import numpy as np
import pytest

from deepcharuco import BoardSpec, Camera, Detector, project_corners
from deepcharuco.boards.synthetic import look_at_pose, paint_markers, render_board_view
from deepcharuco.detection.markers import placement, settling, verification
from deepcharuco.networks.cells import CellCandidates
from evaluate.paper.false_positives import look_alikes

# 12x9 squares of DICT_4X4_1000 at ~15 px: at blur k = 10 few markers read best as themselves.
SMALL_MARKERS = BoardSpec(squares_x=12, squares_y=9, square_length=0.02, marker_length=0.015,
                          dictionary="DICT_4X4_1000")
CAMERA = Camera.from_fov(320, 240, hfov_deg=60.0)


def view(board: BoardSpec, fill: float = 0.9, paint=None, **pose):
    distance = CAMERA.K[0, 0] * max(board.size_m) / (fill * 240)
    rvec, tvec = look_at_pose(board, distance, **pose)
    image = render_board_view(board, CAMERA.K, rvec, tvec, (320, 240), paint=paint)
    rotation, _ = cv2.Rodrigues(rvec)
    return image, project_corners(board, rvec, tvec, CAMERA.K), CAMERA.K @ np.c_[rotation[:, :2], tvec]


def blur(image: np.ndarray, k: int = 10) -> np.ndarray:
    return cv2.filter2D(image, -1, np.ones((1, k), np.float32) / k, borderType=cv2.BORDER_REFLECT)


def test_rank_z_counts_standard_errors_above_chance():
    assert verification.rank_z(np.zeros(0)) == 0.0
    assert verification.rank_z(np.full(10, 0.5)) == pytest.approx(0.0)
    assert verification.rank_z(np.ones(12)) == pytest.approx(6.0)  # (1 - 0.5) * sqrt(12 * 12)
    assert verification.rank_z(np.zeros(12)) == pytest.approx(-6.0)


@pytest.mark.parametrize("best, ranks, chosen_by, verified", [
    (3, 0.95, None, True),         # 3 of 40 read best (the fraction rule refuses), all rank near the top
    (3, 0.95, "all", False),       # ... but only the squares that chose the view say so
    (3, "uniform", None, False),   # ranks at chance: a look-alike
    (1, 0.95, None, False),        # fewer than MIN_MARKERS read best as themselves
])
def test_view_verified_by_ranks_beside_the_fraction_rule(monkeypatch, best, ranks, chosen_by, verified):
    board = SMALL_MARKERS
    readable = np.arange(40)
    reads_best = np.arange(40) < best
    rank = np.linspace(0, 1, 40) if ranks == "uniform" else np.full(40, ranks)
    monkeypatch.setattr(verification, "_ranks_of", lambda *args: (readable, reads_best, rank))
    ids = placement.board_markers(board).ids if chosen_by == "all" else None
    assert verification.view_is_verified(np.zeros((240, 320), np.uint8), board, np.eye(3), chosen_by=ids) is verified


def test_blurred_small_markers_verified_by_rank(monkeypatch):
    image, truth, homography = view(SMALL_MARKERS, tilt_x_deg=20, tilt_y_deg=-10, roll_deg=5)
    blurred = blur(image)
    agreeing, readable = verification.marker_agreement(blurred, SMALL_MARKERS, homography)
    assert agreeing < verification.MIN_MARKER_AGREEMENT * readable  # the fraction rule alone refuses the right view
    assert verification.view_is_verified(blurred, SMALL_MARKERS, homography)
    detector = Detector(board=SMALL_MARKERS)
    found = detector.detect(blurred)
    moved = truth + np.array([0.5, 0.0])  # OpenCV's even kernel shifts the content by half a pixel
    assert len(found.ids) >= 0.8 * SMALL_MARKERS.num_corners
    assert np.linalg.norm(found.corners - moved[found.ids], axis=1).max() < 3.0
    monkeypatch.setattr(verification, "MIN_RANK_Z", np.inf)  # without the rank rule: nothing
    assert len(detector.detect(blurred).ids) == 0


def assert_look_alike_refused(target: BoardSpec, name: str, degradations, **view_args) -> None:
    """``target``'s look-alike ``name`` (`look_alikes`), at two poses and each of ``degradations``: no corner, and
    its true view not verified as ``target``'s."""
    board, paint = look_alikes(target)[name]
    painter = None if isinstance(paint, str) else (lambda texture: paint_markers(texture, paint))
    detector = Detector(board=target)
    for pose in (dict(tilt_x_deg=20, tilt_y_deg=-10, roll_deg=5), dict(tilt_x_deg=-25, tilt_y_deg=15, roll_deg=190)):
        image, _, homography = view(board, paint=painter, **view_args, **pose)
        for degrade in degradations:
            degraded = degrade(image)
            assert len(detector.detect(degraded).ids) == 0
            assert not verification.view_is_verified(degraded, target, homography)


@pytest.mark.parametrize("name", ["other marker IDs", "mirrored", "other dictionary DICT_5X5_250"])
def test_blurred_look_alikes_stay_refused(name):
    assert_look_alike_refused(SMALL_MARKERS, name, (lambda image: image, blur))


def test_weak_cells_start_below_every_threshold():
    # The shipped networks' thresholds (0.1-0.5) keep WEAK_CONFIDENCE; a low one (a distilled network's) keeps weak
    # cells below it, so that its fill-ins are still checked by their neighbours.
    assert [placement.weak_confidence(t) for t in (0.95, 0.5, 0.25, 0.1)] == [placement.WEAK_CONFIDENCE] * 4
    assert placement.weak_confidence(0.03) == pytest.approx(0.015)
    assert all(0 < placement.weak_confidence(t) < t for t in (0.01, 0.02, 0.05, 0.1, 0.95))


@pytest.mark.parametrize("threshold, weak", [(0.25, 0.1), (0.03, 0.02)])
def test_weak_candidates_fill_in_corners_of_the_verified_view_only(threshold, weak):
    board = BoardSpec(squares_x=7, squares_y=5, square_length=0.04, marker_length=0.03, dictionary="DICT_6X6_250")
    image, truth, _ = view(board, fill=0.8, tilt_x_deg=20, tilt_y_deg=-15, roll_deg=10)
    missing = 8  # an inner corner: its neighbours on the board are found
    pixels = np.round(truth).astype(np.float32)
    confidence = np.full(len(truth), 0.9, np.float32)
    confidence[missing] = weak
    spurious = np.array([[5.0, 5.0], [np.round((truth[0, 0] + truth[1, 0]) / 2), np.round(truth[0, 1]) + 40]],
                        np.float32)  # weak points where the view puts no corner
    candidates = CellCandidates(np.r_[pixels, spurious], np.r_[confidence, [weak, weak]].astype(np.float32),
                                np.zeros((len(truth) + 2, 0), np.float32))
    (ids, found, scores), marker_view = placement.corners_from_markers(image, board, candidates, threshold=threshold)
    assert marker_view is not None
    assert sorted(ids.tolist()) == list(range(board.num_corners))  # the weak corner is in, the spurious points not
    assert np.allclose(found[ids == missing], pixels[missing]) and scores[ids == missing] == pytest.approx(weak)
    assert list(scores) == sorted(scores, reverse=True)
    strong = confidence >= threshold
    (ids, _, _), _ = placement.corners_from_markers(
        image, board, CellCandidates(pixels[strong], confidence[strong], np.zeros((int(strong.sum()), 0), np.float32)))
    assert missing not in ids.tolist()  # without the weak candidates the corner stays missing
    # Weak candidates alone find no view: they only fill in.
    weak_only = CellCandidates(pixels, np.full(len(truth), weak, np.float32), np.zeros((len(truth), 0), np.float32))
    assert len(placement.corners_from_markers(image, board, weak_only, threshold=threshold)[0][0]) == 0


def test_a_weak_candidate_fills_in_a_corner_only_where_the_view_and_the_neighbours_agree(monkeypatch):
    # Four found neighbours fit a homography exactly whatever their error: in a motion-blurred frame such a fit put a
    # corner a square from its place, where another weak candidate lay (a drawn validation video).
    board = BoardSpec(squares_x=7, squares_y=5, square_length=0.04, marker_length=0.03, dictionary="DICT_6X6_250")
    _, truth, homography = view(board, fill=0.8, tilt_x_deg=20, tilt_y_deg=-15, roll_deg=10)
    board_xy = board.corner_points()[:, :2]
    missing, next_one = 8, 9
    found = np.delete(np.arange(board.num_corners), missing)
    detection = (found, truth[found].astype(np.float32), np.full(len(found), 0.9, np.float32))
    # weak points at the missing corner and a square along, beside its found neighbour
    weak = CellCandidates(np.array([truth[missing], truth[next_one] + [1.0, 0.0]], np.float32),
                          np.full(2, 0.1, np.float32), np.zeros((2, 0), np.float32))
    board_view = placement.BoardView(homography=homography, inliers=np.ones(len(board_xy), bool))
    ids, pixels, _ = placement._fill_in(board_view, board_xy, detection, weak, (320, 240))
    assert missing in ids.tolist() and np.allclose(pixels[ids == missing], truth[missing])  # both agree: filled in
    monkeypatch.setattr(placement, "_agreed_places", lambda xy, targets, ids, pixels: (
        targets == missing, truth[[next_one]]))  # the neighbours' fit a square off, onto the other point
    ids, _, _ = placement._fill_in(board_view, board_xy, detection, weak, (320, 240))
    assert missing not in ids.tolist()


def test_filled_in_corners_refined_away_from_their_neighbours_are_left_out():
    board = BoardSpec(squares_x=7, squares_y=5, square_length=0.04, marker_length=0.03, dictionary="DICT_6X6_250")
    _, truth, _ = view(board, fill=0.8, tilt_x_deg=20, tilt_y_deg=-15, roll_deg=10)
    board_xy = board.corner_points()[:, :2]  # 6 x 4 corners
    ids = np.arange(board.num_corners)
    scores = np.full(len(ids), 0.9, np.float32)
    scores[[7, 8]] = 0.1  # two filled-in corners (below the threshold), inner ones
    corners = truth.astype(np.float32).copy()
    corners[23] += 2.0  # a confident corner as far off at the board's corner: its neighbours all on one side, unchecked
    agree = settling.FILL_IN_AGREE_PX
    corners[7] += [0.6 * agree, 0.0]  # within the limit of where its neighbours put it: kept
    corners[8] += [0.0, 1.25 * agree]  # beyond it (a corner washed out by glare, refined onto the glare): dropped
    kept_ids, kept, kept_scores = settling.settle_corners(board_xy, ids, corners, scores, threshold=0.25)
    assert kept_ids.tolist() == [i for i in ids.tolist() if i != 8]  # order kept
    assert np.array_equal(kept, np.delete(corners, 8, axis=0)) and np.array_equal(kept_scores, np.delete(scores, 8))
    # In the dark every corner scatters: where the confident neighbours scatter ~1 px about their own fit, a fill-in
    # 1.6 px off is as good as they are and stays.
    noisy = corners + np.random.default_rng(0).normal(0.0, 1.0, corners.shape).astype(np.float32)
    noisy[7], noisy[8] = truth[7], truth[8] + [0.0, 1.6 * agree]
    assert 8 in settling.settle_corners(board_xy, ids, noisy, scores, threshold=0.25)[0].tolist()
    # The same corners all confident: 1.25 px is within the looser limit for a corner the point head is sure of.
    assert 1.25 * agree < settling.OUTLYING_PX
    out = settling.settle_corners(board_xy, ids, corners, np.full(len(ids), 0.9, np.float32), threshold=0.25)
    assert len(out[0]) == len(ids)
    # A fill-in with fewer than 4 confident corners within LOCAL_SQUARES squares cannot be checked: dropped.
    alone = np.array([0, 1, 6, 7]), truth[[0, 1, 6, 7]].astype(np.float32), np.array([0.9, 0.9, 0.9, 0.1], np.float32)
    assert settling.settle_corners(board_xy, *alone, threshold=0.25)[0].tolist() == [0, 1, 6]


def test_local_predictions_match_opencv_homographies():
    board = BoardSpec(squares_x=12, squares_y=9, square_length=0.03, marker_length=0.022, dictionary="DICT_4X4_1000")
    _, truth, _ = view(board, fill=0.9, tilt_x_deg=40, tilt_y_deg=-25, roll_deg=20)  # strong perspective
    noisy = truth + np.random.default_rng(3).normal(0.0, 0.2, truth.shape)
    board_xy = board.corner_points()[:, :2]
    grid = np.rint(board_xy / board.square_length)  # 11 x 8 corners, places in squares
    target, others = 40, np.array([28, 29, 30, 39, 41, 50, 51, 52, 17, 62])  # 8 around it, 2 two squares away
    homography, _ = cv2.findHomography(board_xy[others], noisy[others], 0)
    expected = cv2.perspectiveTransform(board_xy[[target]][None], homography)[0, 0]
    misfit = cv2.perspectiveTransform(board_xy[others][None], homography)[0] - noisy[others]
    expected_scatter = np.sqrt(np.sum(misfit ** 2) / (2 * len(others) - 8))
    # Two slots empty (weight 0, garbage in them): they must not count.
    offsets = np.r_[grid[others] - grid[target], [[5.0, 5.0], [-3.0, 7.0]]][None]
    image = np.r_[noisy[others], [[0.0, 0.0], [1e4, -1e4]]][None]
    weight = np.r_[np.ones(len(others)), [0.0, 0.0]][None]
    predicted, misfit = settling.local_predictions(offsets, weight, image)
    # Least squares on the normalised linear equations vs OpenCV's refined fit: the same to well under 0.05 px.
    assert np.linalg.norm(predicted[0] - expected) < 0.05
    assert np.all(misfit[0, -2:] == 0.0)
    scatter = settling._scatter(misfit, weight)[0]
    assert abs(scatter - expected_scatter) < 0.02 and 0.1 < scatter < 0.4


def test_confident_corners_refined_away_from_their_neighbours_are_left_out():
    board = BoardSpec(squares_x=7, squares_y=5, square_length=0.04, marker_length=0.03, dictionary="DICT_6X6_250")
    _, truth, _ = view(board, fill=0.8, tilt_x_deg=20, tilt_y_deg=-15, roll_deg=10)
    board_xy = board.corner_points()[:, :2]  # 6 x 4 corners, ID = row * 6 + column
    ids = np.arange(board.num_corners)
    scores = np.full(len(ids), 0.9, np.float32)
    corners = truth.astype(np.float32).copy()
    limit = settling.OUTLYING_PX
    corners[3] += [1.3 * limit, 0.0]  # on the top row, neighbours either side along it: checked, dropped (glare)
    corners[14] += [0.0, 0.6 * limit]  # inside, within the limit: kept
    corners[0] += [2.0 * limit, 0.0]  # the board's corner: its neighbours all on one side, unchecked, kept
    kept_ids, kept, kept_scores = settling.settle_corners(board_xy, ids, corners, scores, threshold=0.25)
    assert kept_ids.tolist() == [i for i in ids.tolist() if i != 3]  # order kept
    assert np.array_equal(kept, np.delete(corners, 3, axis=0)) and np.array_equal(kept_scores, np.delete(scores, 3))
    # Below the threshold (a fill-in) the same corner meets the stricter limit: dropped too.
    weak = scores.copy()
    weak[3] = 0.1
    assert 3 not in settling.settle_corners(board_xy, ids, corners, weak, threshold=0.25)[0].tolist()
    # In the dark every corner scatters: where the neighbours scatter ~1 px about their own fit, a corner 2 px off
    # is as good as they are and stays.
    noisy = truth + np.random.default_rng(0).normal(0.0, 1.0, truth.shape).astype(np.float32)
    noisy[3] = truth[3] + [1.3 * limit, 0.0]
    assert 3 in settling.settle_corners(board_xy, ids, noisy, scores, threshold=0.25)[0].tolist()
    # One row of corners: nothing spans both board axes, nothing is checked.
    row = np.arange(6)
    kept_ids = settling.settle_corners(board_xy, row, corners[row], scores[row], threshold=0.25)[0]
    assert kept_ids.tolist() == row.tolist()


def test_corners_far_from_the_others_are_left_out_of_large_detections():
    board = BoardSpec(squares_x=12, squares_y=9, square_length=0.03, marker_length=0.022, dictionary="DICT_4X4_1000")
    board_xy = board.corner_points()[:, :2]  # 11 x 8 corners, ID = row * 11 + column
    block = np.array([row * 11 + column for row in range(3) for column in range(4)])  # a 4 x 3 block: 12 corners
    lone, pair = np.array([10]), np.array([84, 85])  # 6 columns from the block; two neighbours, 5 rows from it
    ids = np.concatenate([block, lone, pair])
    corners = (board_xy[ids] * 1000).astype(np.float32)
    scores = np.linspace(1.0, 0.5, len(ids)).astype(np.float32)
    kept_ids, kept, kept_scores = settling.drop_isolated(board_xy, ids, corners, scores)
    # Each of the pair has 1 neighbour, the lone corner none: fewer than MIN_NEIGHBOURS (3); each of the block's corners
    # has 8 within LOCAL_SQUARES squares and stays.
    assert settling.MIN_NEIGHBOURS == 3 and kept_ids.tolist() == block.tolist()
    assert np.array_equal(kept, corners[:12]) and np.array_equal(kept_scores, scores[:12])
    # A detection smaller than ISOLATION_MIN_CORNERS (darkness, a small board) is left as it is.
    small = np.concatenate([block[:4], pair])
    assert len(small) < settling.ISOLATION_MIN_CORNERS
    assert settling.drop_isolated(board_xy, small, (board_xy[small] * 1000).astype(np.float32),
                                   np.ones(len(small), np.float32))[0].tolist() == small.tolist()


def test_agreement_test_is_the_pixel_distance_without_division():
    rng = np.random.default_rng(4)
    mapped = rng.normal(size=(5, 3, 7)) * [[10.0], [10.0], [1.0]]  # some w negative
    observed = rng.normal(size=(7, 2)) * 10.0
    reach = rng.uniform(1.0, 20.0, size=7)
    with np.errstate(divide="ignore", invalid="ignore"):
        expected = np.hypot(*(mapped[:, :2] / mapped[:, 2:] - observed.T[None]).transpose(1, 0, 2)) < reach
    np.testing.assert_array_equal(placement._lands_within(mapped, observed, reach), expected)
    at_infinity = np.array([[[3.0], [4.0], [0.0]]])  # w = 0: a point at infinity lands nowhere
    with np.errstate(invalid="ignore"):
        assert not placement._lands_within(at_infinity, np.zeros((1, 2)), np.array([1e9]))[0, 0]
        assert not placement._lands_within(np.ones((1, 3, 1)), np.full((1, 2), np.inf), np.array([1e9]))[0, 0]


def test_sampled_maps_equal_the_point_list_sampler_at_any_map_size():
    from deepcharuco.detection.markers.marker_reader import MAX_REMAP_SIDE, _sample, sample_maps

    rng = np.random.default_rng(4)
    gray = rng.integers(0, 256, (60, 80), dtype=np.uint8)
    for shape in [(7, 13), (2, MAX_REMAP_SIDE + 5)]:  # the second goes through `_sample`'s rows
        x = rng.uniform(-3, 83, shape).astype(np.float32)
        y = rng.uniform(-3, 63, shape).astype(np.float32)
        expected = _sample(gray, np.stack([x.ravel(), y.ravel()], axis=1)).reshape(shape)
        np.testing.assert_array_equal(sample_maps(gray, x, y), expected)


# A 3x3 board: 4 corners, 4 markers. Its markers cannot prove the view by ranking among the board's own (4 of 4
# agreeing is a 1.5e-5 chance), so their codes do (`verification.code_errors`).
TINY = BoardSpec(squares_x=3, squares_y=3, square_length=0.04, marker_length=0.03, dictionary="DICT_5X5_100")


def test_code_chance_needs_two_close_codes_and_half_the_readable_ones():
    assert verification.code_error_limit(TINY) == 2  # DICT_5X5_100 corrects 3 bits; 25 bits allow 2
    assert verification.code_error_limit(SMALL_MARKERS) == 0  # DICT_4X4_1000 corrects none
    assert verification.code_chance(np.array([0, 9, 9, 9]), 25, 2) == 1.0  # one close code
    assert verification.code_chance(np.array([0, 1, 9, 9, 9]), 25, 2) == 1.0  # two, but fewer than half
    assert verification.code_chance(np.array([0, 2, 9]), 25, 2) == pytest.approx((1 / 2 ** 25) * (326 / 2 ** 25))


def test_a_3x3_board_in_a_5_megapixel_frame_is_found_by_its_codes():
    from evaluate.speed.realistic import Placement, clutter, with_board

    rng = np.random.default_rng(5)
    detector = Detector(board=TINY)
    found = 0
    for i in range(4):
        frame = with_board(TINY, clutter(rng, (2592, 1944)), rng, Placement(0.1, 0.15), f"tiny {i}")
        detection = detector.detect(frame.image)
        if len(detection.ids):
            found += 1
            assert len(detection.ids) == 4
            assert np.linalg.norm(detection.corners - frame.corners[detection.ids], axis=1).max() < 3.0
    assert found >= 3


@pytest.mark.parametrize("name", ["other marker IDs", "mirrored", "other dictionary DICT_6X6_250"])
def test_a_3x3_look_alike_is_refused(name):
    assert_look_alike_refused(TINY, name, (lambda image: image,), fill=0.5)


def _board_to_pixels(board: BoardSpec, homography: np.ndarray, shift: tuple[float, float]) -> np.ndarray:
    """``homography`` (board metres -> pixels) followed by a shift of the image by ``shift`` px."""
    return np.array([[1.0, 0, shift[0]], [0, 1.0, shift[1]], [0, 0, 1.0]]) @ homography


def test_an_expected_view_names_the_corners_without_the_search_through_the_cells(monkeypatch):
    """A video's board a few pixels from where the frame before put it: the view moved onto the candidates names
    the same corners the search finds, and the cells are never searched."""
    board = BoardSpec(squares_x=7, squares_y=5, square_length=0.04, marker_length=0.03, dictionary="DICT_6X6_250")
    image, truth, homography = view(board, fill=0.8, tilt_x_deg=20, tilt_y_deg=-15, roll_deg=10)
    pixels = np.round(truth).astype(np.float32)
    candidates = CellCandidates(pixels, np.full(len(truth), 0.9, np.float32), np.zeros((len(truth), 0), np.float32))
    searched = placement.corners_from_markers(image, board, candidates)[0]
    board_xy = board.corner_points()[:, :2]
    moved = placement.view_near(_board_to_pixels(board, homography, (4.0, -3.0)), board_xy, pixels)
    assert np.abs(placement.apply_homography(moved.homography, board_xy)[0] - truth).max() < 1.0

    def no_search(*args, **kwargs):
        raise AssertionError("the cells were searched")
    monkeypatch.setattr(placement, "find_cells", no_search)
    (ids, found, _), marker_view = placement.corners_from_markers(
        image, board, candidates, expected=_board_to_pixels(board, homography, (4.0, -3.0)))
    assert marker_view is not None and np.array_equal(ids, searched[0]) and np.array_equal(found, searched[1])


@pytest.mark.parametrize("second_pass_view, checks", [("the same", 1), ("another", 2)])
def test_a_view_the_checks_refused_is_not_checked_again_by_the_second_pass(monkeypatch, second_pass_view, checks):
    """The search's second pass (every cell) finding the view its first (the squarest cells) found and the checks
    refused: refused again without reading its markers again; another view is checked."""
    board = BoardSpec(squares_x=7, squares_y=5, square_length=0.04, marker_length=0.03, dictionary="DICT_6X6_250")
    candidates = CellCandidates(np.zeros((8, 2), np.float32), np.full(8, 0.9, np.float32), np.zeros((8, 0), np.float32))
    monkeypatch.setattr(placement, "find_cells", lambda pixels: np.zeros((2, 4), np.int64))
    monkeypatch.setattr(placement, "squarest_rows", lambda pixels, quads: np.arange(1))
    first = placement.MarkerView(view=placement.BoardView(homography=np.eye(3), inliers=np.ones(4, bool)),
                                 marker_ids=np.array([3, 4]), reads=5)
    again = placement.MarkerView(view=placement.BoardView(homography=np.eye(3), inliers=np.ones(4, bool)),
                                 marker_ids=np.array([3, 4]), reads=7)  # found again, from more reads
    other = placement.MarkerView(view=placement.BoardView(homography=np.diag([2.0, 2.0, 1.0]), inliers=np.ones(4, bool)),
                                 marker_ids=np.array([3, 4]), reads=5)
    views = iter([first, again if second_pass_view == "the same" else other])
    monkeypatch.setattr(placement, "find_marker_view", lambda *args, **kwargs: next(views))
    checked = []
    monkeypatch.setattr(placement, "_verified_corners", lambda *args, **kwargs: checked.append(args[4]))
    (ids, _, _), marker_view = placement.corners_from_markers(np.zeros((240, 320), np.uint8), board, candidates)
    assert len(ids) == 0 and marker_view is None and len(checked) == checks


def test_a_wrong_expected_view_is_refused_by_the_markers_and_the_cells_searched():
    """An expected view two squares off (its corners land on other corners of the board, its markers on other
    markers): the markers refuse it, the search through the cells finds the board as without it."""
    board = BoardSpec(squares_x=7, squares_y=5, square_length=0.04, marker_length=0.03, dictionary="DICT_6X6_250")
    image, truth, homography = view(board, fill=0.8, tilt_x_deg=20, tilt_y_deg=-15, roll_deg=10)
    pixels = np.round(truth).astype(np.float32)
    candidates = CellCandidates(pixels, np.full(len(truth), 0.9, np.float32), np.zeros((len(truth), 0), np.float32))
    two_squares = np.array([[1.0, 0, 2 * board.square_length], [0, 1.0, 0], [0, 0, 1.0]])
    wrong = homography @ two_squares
    board_xy = board.corner_points()[:, :2]
    assert placement.view_near(wrong, board_xy, pixels) is not None  # it does land on candidates
    (ids, found, _), marker_view = placement.corners_from_markers(image, board, candidates, expected=wrong)
    searched = placement.corners_from_markers(image, board, candidates)[0]
    assert marker_view is not None and np.array_equal(ids, searched[0]) and np.array_equal(found, searched[1])
    assert np.abs(found - truth[ids]).max() < 1.0


@pytest.mark.parametrize("dictionary", ["DICT_4X4_1000", "DICT_6X6_250", "DICT_7X7_50"])
def test_code_words_count_the_bits_that_differ(dictionary):
    # The layout check compares reads with every code of the dictionary by XOR and popcount of bit words: the same
    # counts as comparing the bits one by one, up to 49-bit (7x7) codes.
    codes = verification.dictionary_codes(dictionary)
    reads = np.random.default_rng(0).random((20, codes.shape[1])) > 0.5
    reads[:3] = codes[[0, 5, len(codes) - 1]]  # exact codes: 0 bits off
    reads[3] = ~codes[1]  # every bit off
    counted = verification._popcount(verification._code_words(reads)[:, None]
                                     ^ verification.dictionary_words(dictionary)[None, :])
    assert np.array_equal(counted, np.sum(reads[:, None, :] != codes[None, :, :], axis=2))
    assert counted[:3].min(axis=1).tolist() == [0, 0, 0] and counted[3, 1] == codes.shape[1]


def test_dictionary_codes_are_opencvs_bits_in_every_quarter_turn():
    # Unpacked for all markers at once: OpenCV's own bits (getBitsFromByteList) of each marker, turned as np.rot90 turns.
    for name in ("DICT_4X4_50", "DICT_5X5_100", "DICT_6X6_250", "DICT_7X7_50", "DICT_ARUCO_ORIGINAL",
                 "DICT_APRILTAG_36h11"):
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
        size = dictionary.markerSize
        expected = [np.rot90(cv2.aruco.Dictionary.getBitsFromByteList(dictionary.bytesList[i:i + 1], size) > 0, turn)
                    for i in range(len(dictionary.bytesList)) for turn in range(4)]
        assert np.array_equal(verification.dictionary_codes(name), np.reshape(expected, (len(expected), -1))), name
