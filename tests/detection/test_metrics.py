import numpy as np

from deepcharuco import Detection, match_corners

TRUTH = np.stack(np.meshgrid(np.arange(4) * 30.0 + 100, np.arange(4) * 30.0 + 60), -1).reshape(16, 2)


def detection_of(ids, shift=(0.0, 0.0)):
    ids = np.asarray(ids)
    return Detection(ids, TRUTH[ids] + np.asarray(shift), np.ones(len(ids)))


def test_perfect_detector_scores_one():
    match = match_corners(detection_of(range(16)), TRUTH)
    assert match.accuracy == 1.0 and match.num_correct == 16
    np.testing.assert_allclose(match.subpixel_errors, 0.0)


def test_three_pixel_rule():
    assert match_corners(detection_of(range(16), (2.0, 2.0)), TRUTH).accuracy == 1.0  # 2.83 px
    assert match_corners(detection_of(range(16), (2.2, 2.2)), TRUTH).accuracy == 0.0  # 3.11 px
    assert match_corners(detection_of(range(16), (3.0, 0.0)), TRUTH).accuracy == 0.0  # not < 3


def test_accuracy_divides_by_all_board_corners():
    match = match_corners(detection_of([0, 1, 2, 3]), TRUTH)
    assert match.accuracy == 4 / 16


def test_wrong_ids_do_not_count():
    swapped = Detection([0, 1], TRUTH[[1, 0]], np.ones(2))
    assert match_corners(swapped, TRUTH).accuracy == 0.0
    unknown = Detection([16, 40], TRUTH[[0, 1]], np.ones(2))
    match = match_corners(unknown, TRUTH)
    assert match.accuracy == 0.0 and np.all(np.isinf(match.errors))


def test_corners_without_truth_or_invisible_are_wrong():
    truth = TRUTH.copy()
    truth[5] = np.nan
    visible = np.ones(16, bool)
    visible[6] = False
    match = match_corners(detection_of(range(16)), truth, visible)
    assert match.num_correct == 14
    assert not match.correct[5] and not match.correct[6]


def test_subpixel_errors_are_of_correct_corners_only():
    corners = TRUTH[:3].copy()
    corners[0] += (0.3, 0.4)
    corners[2] += (10, 0)
    match = match_corners(Detection([0, 1, 2], corners, np.ones(3)), TRUTH)
    np.testing.assert_allclose(match.subpixel_errors, [0.5, 0.0], atol=1e-5)
