"""The board-geometry check: wrong IDs dropped, unsure IDs recovered, impossible views refused."""

import numpy as np
import pytest

from deepcharuco import BoardSpec, Detection
from deepcharuco.detection.board_check import MIN_CONSENSUS, assign_ids, fit_board_homography, id_hypotheses
from deepcharuco.networks.cells import CellCandidates

BOARD = BoardSpec()
BOARD_XY = BOARD.corner_points()[:, :2]
IMAGE_SIZE = (320, 240)


def candidates_at(pixels: np.ndarray, first: np.ndarray, second: np.ndarray | None = None) -> CellCandidates:
    """Cells at ``pixels`` whose ID head says ``first`` (p = 0.4) and ``second`` (p = 0.3) or spreads the rest."""
    n = BOARD.num_corners
    prob = np.full((len(pixels), n), 0.3 / (n - 2), np.float32)
    prob[np.arange(len(pixels)), first] = 0.4
    if second is not None:
        prob[np.arange(len(pixels)), second] = 0.3
    return CellCandidates(np.round(pixels).astype(np.float32), np.full(len(pixels), 0.9, np.float32), prob)


def test_hypotheses_are_each_cells_likeliest_ids():
    cells = candidates_at(np.array([[10.0, 20.0], [30.0, 40.0]]), np.array([3, 7]), np.array([5, 1]))
    ids, pixels = id_hypotheses(cells, per_cell=2)
    assert ids.tolist() == [3, 5, 7, 1]
    assert pixels.tolist() == [[10, 20], [10, 20], [30, 40], [30, 40]]
    sure = CellCandidates(cells.pixels, cells.confidence, cells.id_prob.copy())
    sure.id_prob[1] = 0.0005
    sure.id_prob[1, 7] = 0.99  # the ID head is sure of the second cell: its second ID is not proposed
    ids, pixels = id_hypotheses(sure, per_cell=2, min_prob=0.001)
    assert ids.tolist() == [3, 5, 7] and pixels.tolist() == [[10, 20], [10, 20], [30, 40]]


@pytest.mark.parametrize("view", range(5))
def test_repair_recovers_every_corner_when_a_third_of_the_ids_are_wrong(default_views, view):
    """Truth from a synthetic view; the ID head's first choice is wrong for 5 corners (its second is right):
    the view is verified from the 11 right pairs and every corner gets its true ID, at its true pixel."""
    _, _, _, truth = default_views[view]
    ids = np.arange(BOARD.num_corners)
    wrong = np.random.default_rng(view).choice(ids, 5, replace=False)
    first = ids.copy()
    first[wrong] = (ids[wrong] + 5) % BOARD.num_corners
    cells = candidates_at(truth, first, np.where(np.isin(ids, wrong), ids, (ids + 1) % BOARD.num_corners))
    proposed_ids, proposed_pixels = id_hypotheses(cells)
    found = fit_board_homography(BOARD_XY[proposed_ids], proposed_pixels)
    assert found is not None and found.inliers.sum() == BOARD.num_corners
    got_ids, got_pixels, scores = assign_ids(found, BOARD_XY, cells, IMAGE_SIZE)
    assert sorted(got_ids.tolist()) == ids.tolist()
    np.testing.assert_allclose(got_pixels, np.round(truth[got_ids]), atol=1e-6)
    assert np.all(scores == 0.9)


def test_filter_keeps_the_consensus_and_names_the_wrong_ids(default_views):
    _, _, _, truth = default_views[1]
    ids = np.arange(BOARD.num_corners)
    claimed = ids.copy()
    claimed[[2, 9]] = [9, 2]  # two corners swapped
    found = fit_board_homography(BOARD_XY[claimed], truth)
    assert found is not None
    assert np.flatnonzero(~found.inliers).tolist() == [2, 9]


def test_a_mirrored_board_is_not_a_view(default_views):
    """IDs mirrored left-right fit a homography exactly, but one that flips the board: refused."""
    _, _, _, truth = default_views[0]
    columns = BOARD.squares_x - 1
    mirrored = np.array([(i // columns) * columns + (columns - 1 - i % columns) for i in range(BOARD.num_corners)])
    assert fit_board_homography(BOARD_XY[mirrored], truth) is None
    assert fit_board_homography(BOARD_XY, truth) is not None


def test_too_few_or_collinear_pairs_verify_nothing(default_views):
    _, _, _, truth = default_views[2]
    few = np.arange(MIN_CONSENSUS - 1)
    assert fit_board_homography(BOARD_XY[few], truth[few]) is None
    columns = BOARD.squares_x - 1
    one_row = np.arange(columns)  # a whole row of the 4x4 grid plus nothing else
    assert fit_board_homography(np.repeat(BOARD_XY[one_row], 2, axis=0), np.repeat(truth[one_row], 2, axis=0)) is None


def test_assign_ids_skips_corners_outside_the_image_and_far_cells(default_views):
    _, _, _, truth = default_views[0]
    found = fit_board_homography(BOARD_XY, truth)
    shifted = truth.copy()
    shifted[4] += 3.5  # the cell found near corner 4 is 5 px away: not corner 4
    cells = candidates_at(shifted, np.arange(BOARD.num_corners))
    ids, _, _ = assign_ids(found, BOARD_XY, cells, IMAGE_SIZE)
    assert 4 not in ids.tolist() and len(ids) == BOARD.num_corners - 1
    # Crop the image so that the left column of corners falls outside it.
    left = int(np.ceil(truth[:, 0].min()))
    cropped = found.homography.copy()
    cropped[0] -= left * cropped[2]
    inside = truth[:, 0] - left > -0.5
    cells = candidates_at(truth[inside] - [left, 0], np.flatnonzero(inside))
    view = type(found)(cropped, found.inliers)
    ids, _, _ = assign_ids(view, BOARD_XY, cells, (IMAGE_SIZE[0] - left, IMAGE_SIZE[1]))
    assert sorted(ids.tolist()) == np.flatnonzero(inside).tolist()


def test_detector_geometry_modes(default_views, camera, backend):
    """On a clean synthetic view the shipped weights find >= 12 corners with the check, all right, and the
    pose follows, on every backend; a detection of fewer than 6 corners gets no pose when the check is on."""
    from deepcharuco import Detector
    from evaluate.paper.protocols import rotation_error_deg

    image, rvec, tvec, truth = default_views[0]
    repaired = Detector(geometry="repair", backend=backend).detect(image)
    assert len(repaired) >= 12
    assert np.all(np.linalg.norm(repaired.corners - truth[repaired.ids], axis=1) < 1.0)
    detector = Detector()
    pose = detector.estimate_pose(repaired, camera.K)
    assert pose is not None and rotation_error_deg(pose.rvec, rvec) < 2.0
    pick = np.array([0, 3, 6, 12, 15])  # spread over the board, at their true pixels
    few = Detection(ids=pick, corners=truth[pick].astype(np.float32), scores=np.ones(5, np.float32))
    assert detector.estimate_pose(few, camera.K) is None
    assert Detector(geometry="none").estimate_pose(few, camera.K) is not None
    with pytest.raises(ValueError, match="geometry must be one of"):
        Detector(geometry="fix")
