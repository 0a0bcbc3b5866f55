"""The board's printed pattern around a corner (`deepcharuco.detection.junction`) and the corners it fills in where the point
head missed them (`placement._fill_in_by_pattern`, `Detector`): found across a cast shadow's edge, refused under an
occluder or on another corner's place, located to a fraction of a pixel."""

import cv2
import numpy as np
import pytest

from deepcharuco import BoardSpec, Camera, Detector, project_corners
from deepcharuco.boards.print_face import canonical_view
from deepcharuco.boards.synthetic import look_at_pose, render_board_view
from deepcharuco.detection import deep_detector
from deepcharuco.detection.junction import locate_by_pattern, pattern_evidence
from deepcharuco.detection.markers import placement
from deepcharuco.networks.cells import CellCandidates

BOARD = BoardSpec(squares_x=7, squares_y=5, square_length=0.04, marker_length=0.03, dictionary="DICT_6X6_250")
INVERTED = BoardSpec(squares_x=5, squares_y=4, square_length=0.05, marker_length=0.0375, dictionary="DICT_4X4_1000",
                     inverted=True)
CAMERA = Camera.from_fov(320, 240, hfov_deg=60.0)
TARGET = 8  # an inner corner of both boards, with found neighbours all round


def view(board: BoardSpec, fill: float = 0.8):
    distance = CAMERA.K[0, 0] * max(board.size_m) / (fill * 240)
    rvec, tvec = look_at_pose(board, distance, tilt_x_deg=20, tilt_y_deg=-15, roll_deg=10)
    image = render_board_view(board, CAMERA.K, rvec, tvec, (320, 240))
    truth = project_corners(board, rvec, tvec, CAMERA.K)
    homography, _ = cv2.findHomography(board.corner_points()[:, :2], truth.astype(np.float64), 0)
    return image, truth, homography


def shadow_edge(image: np.ndarray, through: np.ndarray, angle_deg: float, level: float = 0.35) -> np.ndarray:
    """A cast shadow's straight edge through ``through``: one side keeps ``level`` of its light (1 px penumbra)."""
    height, width = image.shape
    normal = np.array([-np.sin(np.radians(angle_deg)), np.cos(np.radians(angle_deg))])
    across = (np.arange(width)[None] - through[0]) * normal[0] + (np.arange(height)[:, None] - through[1]) * normal[1]
    gain = level + (1 - level) * 0.5 * (1 + np.tanh(across))
    return np.clip(np.rint(image * gain), 0, 255).astype(np.uint8)


def occluded(image: np.ndarray, at: np.ndarray, radius: float, textured: bool, half_plane: bool = False) -> np.ndarray:
    """A disc of ``radius`` px over ``at`` (or everything beyond a straight line through it: an occluder's outline
    across the corner), plain grey or noise (seeded)."""
    out = image.copy()
    if half_plane:
        height, width = image.shape
        mask = ((np.arange(width)[None] - at[0]) * 0.8 + (np.arange(height)[:, None] - at[1]) * 0.6) > 0
    else:
        canvas = np.zeros_like(image)
        cv2.circle(canvas, tuple(int(v) for v in np.round(at)), int(round(radius)), 255, -1)
        mask = canvas > 0
    cover = np.random.default_rng(0).integers(0, 256, image.shape) if textured else np.full(image.shape, 128)
    out[mask] = cover[mask]
    return out


def square_px(truth: np.ndarray) -> float:
    return float(np.linalg.norm(truth[TARGET + 1] - truth[TARGET]))


@pytest.mark.parametrize("board", [BOARD, INVERTED], ids=["7x5", "5x4 inverted"])
def test_evidence_high_at_every_corner_and_low_half_a_square_off(board):
    image, truth, homography = view(board)
    gray = canonical_view(image, board)
    ids = np.arange(board.num_corners)
    at_corners = pattern_evidence(gray, board, homography, ids, truth)
    assert at_corners.min() >= 3 * placement.PATTERN_MIN_T
    for direction in ((1, 0), (0, 1), (1, 1)):  # onto a square's edge, and into a square
        step = 0.5 * square_px(truth) * np.asarray(direction, np.float64) / np.linalg.norm(direction)
        assert pattern_evidence(gray, board, homography, ids, truth + step).max() < placement.PATTERN_MIN_T


@pytest.mark.parametrize("angle", [0, 35, 90, 140])
def test_evidence_survives_a_shadow_edge_through_the_corner(angle):
    image, truth, homography = view(BOARD)
    shaded = shadow_edge(image, truth[TARGET] + 0.5, angle)
    assert pattern_evidence(shaded, BOARD, homography, [TARGET], truth[[TARGET]])[0] >= placement.PATTERN_MIN_T


@pytest.mark.parametrize("textured", [False, True], ids=["grey", "noise"])
@pytest.mark.parametrize("cover", ["disc", "window", "half"], ids=["the corner's surround", "the whole window",
                                                                  "one side of a line through the corner"])
def test_no_evidence_under_an_occluder(textured, cover):
    """Half a window of pattern is not enough: the side the occluder covers shows none."""
    image, truth, homography = view(BOARD)
    radius = {"disc": 0.45, "window": 1.0, "half": 0.0}[cover] * square_px(truth)
    hidden = occluded(image, truth[TARGET], radius, textured, half_plane=cover == "half")
    assert pattern_evidence(hidden, BOARD, homography, [TARGET], truth[[TARGET]])[0] < placement.PATTERN_MIN_T


def test_evidence_is_minus_infinity_for_a_window_off_the_image():
    image, truth, homography = view(BOARD)
    assert pattern_evidence(image, BOARD, homography, [TARGET], np.array([[1.0, 1.0]]))[0] == -np.inf
    assert pattern_evidence(image, BOARD, homography, [], np.zeros((0, 2))).shape == (0,)


def test_locate_by_pattern_finds_the_corner_in_good_light_and_across_a_shadow_edge():
    image, truth, homography = view(BOARD)
    start = truth + np.random.default_rng(1).uniform(-1.2, 1.2, truth.shape)
    ids = np.arange(BOARD.num_corners)
    located = locate_by_pattern(image, BOARD, homography, ids, start)
    assert np.linalg.norm(located - truth, axis=1).max() < 0.2
    for angle in (20, 70, 120):
        shaded = shadow_edge(image, truth[TARGET] + 0.5, angle, level=0.2)
        located = locate_by_pattern(shaded, BOARD, homography, [TARGET], start[[TARGET]])
        assert np.linalg.norm(located[0] - truth[TARGET]) < 0.3  # at most 0.13 px (2026-11-27)


def candidates_without(truth: np.ndarray, left_out: list[int]) -> CellCandidates:
    keep = np.setdiff1d(np.arange(len(truth)), left_out)
    return CellCandidates(np.round(truth[keep]).astype(np.float32), np.full(len(keep), 0.9, np.float32),
                          np.zeros((len(keep), 0), np.float32))


@pytest.mark.parametrize("board", [BOARD, INVERTED], ids=["7x5", "5x4 inverted"])
def test_a_corner_the_point_head_missed_is_filled_in_across_a_shadow_edge(board, monkeypatch):
    image, truth, _ = view(board)
    shaded = canonical_view(shadow_edge(image, truth[TARGET] + 0.5, 30), board)
    candidates = candidates_without(truth, [TARGET])  # no candidate at all there, not even a weak one
    (ids, pixels, scores), found = placement.corners_from_markers(shaded, board, candidates, threshold=0.25)
    assert found is not None and TARGET in ids
    assert scores[ids == TARGET][0] == placement.PATTERN_SCORE and scores.min() == placement.PATTERN_SCORE
    assert np.linalg.norm(pixels[ids == TARGET][0] - truth[TARGET]) < 0.9  # 0.45 px (7x5), 0.09 px (5x4), 2026-11-27
    monkeypatch.setattr(placement, "PATTERN_MIN_T", np.inf)
    (ids, _, _), _ = placement.corners_from_markers(shaded, board, candidates, threshold=0.25)
    assert TARGET not in ids


def test_an_occluded_corner_is_not_filled_in():
    image, truth, _ = view(BOARD)
    for textured in (False, True):
        hidden = occluded(image, truth[TARGET], 0.45 * square_px(truth), textured)
        (ids, _, _), found = placement.corners_from_markers(hidden, BOARD, candidates_without(truth, [TARGET]),
                                                             threshold=0.25)
        assert found is not None and TARGET not in ids and len(ids) == BOARD.num_corners - 1


def test_no_corner_is_filled_in_where_another_was_found(monkeypatch):
    """A found corner far along the board (not a neighbour, so the local fit is the same) lying where the missing one
    is predicted: the place is taken, whatever the pattern says."""
    image, truth, _ = view(BOARD)
    found_ids = np.setdiff1d(np.arange(BOARD.num_corners), [TARGET])
    pixels = np.round(truth[found_ids]).astype(np.float32)
    far = int(found_ids[-1])
    pixels[found_ids == far] = np.round(truth[TARGET])
    view_ = placement.BoardView(homography=cv2.findHomography(BOARD.corner_points()[:, :2], truth.astype(np.float64),
                                                              0)[0], inliers=np.ones(BOARD.num_corners, bool))
    found = (found_ids, pixels, np.full(len(found_ids), 0.9, np.float32))
    board_xy = BOARD.corner_points()[:, :2]
    ids, _, _ = placement._fill_in_by_pattern(image, BOARD, view_, board_xy, found)
    assert TARGET not in ids
    monkeypatch.setattr(placement, "PATTERN_APART", 0.0)
    ids, _, _ = placement._fill_in_by_pattern(image, BOARD, view_, board_xy, found)
    assert TARGET in ids


def test_detector_places_a_missed_corner_by_the_pattern_not_refinenet(monkeypatch):
    """The point head made to miss one corner under a shadow's edge (its candidate removed): the detector reports it,
    score `PATTERN_SCORE`, where the printed pattern fits, within a fraction of a pixel."""
    image, truth, _ = view(BOARD)
    shaded = shadow_edge(image, truth[TARGET] + 0.5, 60, level=0.25)
    original = deep_detector.cell_candidates

    def missing_target(*args, **kwargs):
        candidates = original(*args, **kwargs)
        far = np.linalg.norm(candidates.pixels - truth[TARGET], axis=1) > 3
        return candidates.subset(far)

    monkeypatch.setattr(deep_detector, "cell_candidates", missing_target)
    found = Detector(board=BOARD).detect(shaded)
    assert TARGET in found.ids
    assert found.scores[found.ids == TARGET][0] == placement.PATTERN_SCORE
    assert np.linalg.norm(found.corners[found.ids == TARGET][0] - truth[TARGET]) < 0.3
    others = found.ids != TARGET
    assert np.linalg.norm(found.corners[others] - truth[found.ids[others]], axis=1).max() < 0.5
