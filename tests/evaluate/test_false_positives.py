"""The false-positive section: look-alike boards drawn as the target is printed, photos without a board,
and the marker check's chance rule that keeps the deep detector silent on them."""

from dataclasses import replace

import cv2
import numpy as np
import pytest

from conftest import ROOT

from deepcharuco import BoardSpec, Detector, OpenCVDetector
from deepcharuco.cli.detect import make_detector
from deepcharuco.detection.markers.verification import MAX_CHANCE, chance_of_agreement, markers_beyond_contradict
from evaluate.paper.false_positives import board_free_photos, false_positive_experiment, look_alikes, sections, targets


def test_look_alikes_exclude_dictionaries_that_print_the_same_board():
    names = list(look_alikes(BoardSpec()))
    assert "other dictionary DICT_5X5_250" not in names  # DICT_5X5_250 begins with DICT_5X5_50's markers
    assert {"other dictionary DICT_6X6_250", "other marker IDs", "mirrored", "plain chessboard"} <= set(names)
    board, paint = look_alikes(BoardSpec())["other marker IDs"]
    assert board == BoardSpec() and paint.tolist() == list(range(12, 24))


def test_chance_rule_asks_more_markers_of_small_boards():
    assert chance_of_agreement(2, 3, 12) > MAX_CHANCE >= chance_of_agreement(3, 3, 12)  # 12 markers: 3 of 3
    assert chance_of_agreement(2, 3, 200) <= MAX_CHANCE  # 200 markers: 2 of 3 is already rare
    assert chance_of_agreement(0, 5, 12) == pytest.approx(1.0)


def test_markers_beyond_the_edge_refuse_a_view_beyond_chance():
    """A square beyond the board reads as one of a 4x5 DICT_4X4_1000 board's 10 codes (1 bit off allowed) with chance
    10 x 17 / 2^16: one such read of 20 is chance, three of 20 are not; a 22x22 board's 242 codes need more."""
    small, large = BoardSpec(4, 5, 0.05, 0.04, "DICT_4X4_1000"), BoardSpec(22, 22, 0.05, 0.04, "DICT_4X4_1000")
    assert not markers_beyond_contradict(20, 0, small) and not markers_beyond_contradict(20, 1, small)
    assert markers_beyond_contradict(20, 3, small)
    assert not markers_beyond_contradict(20, 3, large) and markers_beyond_contradict(20, 8, large)


def test_photos_are_bundled_gray_uint8():
    photos = board_free_photos()
    assert len(photos) >= 20
    assert all(image.dtype == np.uint8 and image.ndim == 2 and min(image.shape) >= 100 for _, image in photos)


def test_no_pose_on_look_alikes_and_photos_and_the_targets_say_so():
    board = BoardSpec()
    result = false_positive_experiment({"deep": Detector(board=board), "opencv": OpenCVDetector(board)}, board,
                                       views=2, seed=3, quiet=True)
    rows = {row["set"]: row for row in result["table"]}
    assert rows["board-free photos"]["frames"] == len(board_free_photos())
    assert all(row["deep"]["with_pose"] == 0 for row in result["table"])
    assert [(what, met) for what, _, _, met in targets(result)] == [
        ("poses on look-alike boards and board-free photos", True), ("board-free photos with any corner reported", True)]
    (title, _, table, _), = sections(result, {"deep": "deep detector"})
    assert title.startswith("False positives") and table[0] == ["set", "frames", "deep detector: corners / pose",
                                                                 "opencv: corners / pose"]
    assert len(table) == 1 + len(result["table"])
    # The targets can fail: one pose anywhere is a miss.
    rows["mirrored"]["deep"]["with_pose"] = 1
    assert not targets(result)[0][3]


SAMPLES = ROOT / "evaluate" / "captures_sample"


def _layouts(folder: str) -> tuple[BoardSpec, dict[str, BoardSpec], list[np.ndarray]]:
    board = BoardSpec.load(SAMPLES / folder / "board.yaml")
    wrong = {"transposed": replace(board, squares_x=board.squares_y, squares_y=board.squares_x)}
    if folder == "caliscope_cam1":  # IDs two on: every row's markers sit where the next row's are printed
        wrong["shifted"] = replace(board, first_marker_id=board.first_marker_id + 2)
    else:  # IDs one and two on: the view fits every marker it covers; the print's others lie beyond its edge
        wrong["shifted by one"] = replace(board, first_marker_id=board.first_marker_id + 1)
        wrong["shifted by two"] = replace(board, first_marker_id=board.first_marker_id + 2)
    return board, wrong, [cv2.imread(str(p)) for p in sorted((SAMPLES / folder).glob("*.jpg"))]


@pytest.mark.parametrize("folder", ["caliscope_cam1", "opencv_tutorial"])
@pytest.mark.parametrize("name", ["opencv", "deep", "hybrid"])
def test_a_board_file_of_another_layout_with_the_same_ids_is_not_reported(folder, name):
    """Real frames (the shipped samples: caliscope's inverted 4x5 DICT_4X4_1000 board, OpenCV's tutorial 5x7
    DICT_6X6_250) searched with a board file of their IDs in another layout: every detector finds nothing, for
    the markers it reads contradict that layout (`placement.contradicting_markers`; OpenCV's interpolation
    already names no corner that its markers do not back), or the print's own markers lie beyond the edge of the view
    (`verification.layout_ends_short`); the right layout is found in the frames it was before. (The deep and hybrid
    detectors reported 9 corners of a transposed caliscope board at scores 0.94-1.0, 4-7 of the one shifted by two
    rows, and 8-15 of the tutorial board shifted by one or two markers.)"""
    board, wrong, frames = _layouts(folder)
    right = make_detector(name, board, "subpix" if name == "opencv" else "refinenet")
    found = [len(right.detect(frame)) for frame in frames]
    assert sum(n >= 6 for n in found) >= (4 if folder == "caliscope_cam1" else 3)
    for layout, other in wrong.items():
        detector = make_detector(name, other, "subpix" if name == "opencv" else "refinenet")
        # OpenCV names one corner of the transposed caliscope board from two markers that both layouts print
        # around it: that corner is right, and no contradiction.
        assert max(len(detector.detect(frame)) for frame in frames) <= (1 if name == "opencv" else 0), layout



def _markers_swapped(image: np.ndarray, board: BoardSpec, a: int, b: int) -> np.ndarray:
    """``image`` with the printed markers ``a`` and ``b`` exchanged (each warped into the other's quad, as OpenCV's
    marker detector finds them): the board of the frame no longer has its board file's layout."""
    corners, ids, _ = cv2.aruco.ArucoDetector(board.cv_dictionary()).detectMarkers(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY))
    quads = {int(i): c.reshape(4, 2).astype(np.float32) for i, c in zip(ids.ravel(), corners)}
    out = image.copy()
    for source, target in ((a, b), (b, a)):
        warped = cv2.warpPerspective(image, cv2.getPerspectiveTransform(quads[source], quads[target]), image.shape[1::-1])
        inside = np.zeros(image.shape[:2], np.uint8)
        cv2.fillConvexPoly(inside, np.round(quads[target]).astype(np.int32), 255)
        out[inside > 0] = warped[inside > 0]
    return out


@pytest.mark.parametrize("name", ["opencv", "deep", "hybrid"])
def test_a_frame_whose_markers_are_swapped_is_not_reported(name):
    """OpenCV's tutorial photos with two of the board's 17 markers (7 and 8) swapped in the image: the board file's
    layout is contradicted by two clear reads, beyond chance for DICT_6X6_250 (`placement.layout_contradicted`), and
    no detector reports it. (The deep and hybrid detectors reported all 24 corners.)"""
    board, _, frames = _layouts("opencv_tutorial")
    frames = frames[:3]  # the unoccluded photos
    detector = make_detector(name, board, "subpix" if name == "opencv" else "refinenet")
    assert [len(detector.detect(frame)) for frame in frames] == [24, 24, 24]
    assert [len(detector.detect(_markers_swapped(frame, board, 7, 8))) for frame in frames] == [0, 0, 0]


def test_the_layout_sweep_names_the_print_and_its_look_alikes():
    """`python -m evaluate.captures.layouts` (the note's table of shifted layouts) searches each set with these."""
    from evaluate.captures.layouts import layouts

    board = BoardSpec(4, 5, 0.05, 0.04, "DICT_4X4_1000", first_marker_id=3)
    found = layouts(board)
    assert list(found) == ["right", "transposed", "+1", "+2", "+3"] and found["right"] == board
    assert (found["transposed"].squares_x, found["transposed"].squares_y) == (5, 4)
    assert [found[f"+{k}"].first_marker_id for k in (1, 2, 3)] == [4, 5, 6]
