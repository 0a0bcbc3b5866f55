"""The false-positive section: look-alike boards drawn as the target is printed, photos without a board,
and the marker check's chance rule that keeps the deep detector silent on them."""

import numpy as np
import pytest

from deepcharuco import BoardSpec, Detector, OpenCVDetector
from deepcharuco.detection.placement import MAX_CHANCE, chance_of_agreement
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
