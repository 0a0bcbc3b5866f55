"""Drawn validation videos: exact truth in every frame, empty stretches without a board, the same pixels from the
same seed, and a shaken board smeared about its own position."""

import numpy as np
import pytest

from deepcharuco import OpenCVDetector
from evaluate.paper.unseen_boards import UNSEEN_BOARDS
from evaluate.speed.drawn_videos import _smear_kernel, drawn_video

BOARD = UNSEEN_BOARDS["7x5 DICT_6X6_250"]
SIZE = (640, 360)


@pytest.fixture(scope="module")
def good():
    return drawn_video(BOARD, seed=3, frames=60, condition="good", size=SIZE)


def test_opencv_finds_the_corners_where_the_truth_puts_them_and_nothing_in_the_empty_frames(good):
    opencv = OpenCVDetector(BOARD)
    errors, found, empty = [], 0, 0
    for frame, truth, visible in zip(good.frames, good.corners, good.visible):
        detection = opencv.detect(frame)
        if truth is None:
            empty += 1
            assert len(detection) == 0
            continue
        if len(detection):
            found += 1
            assert visible[detection.ids].all()
            errors += list(np.hypot(*(detection.corners - truth[detection.ids]).T))
    assert empty >= 5 and found >= 10
    assert np.median(errors) < 0.15 and max(errors) < 1.0


def test_a_video_has_visits_and_gaps_and_the_same_seed_draws_the_same_pixels(good):
    shows = [good.shows_board(i) for i in range(len(good.frames))]
    assert not shows[0]  # a gap comes first
    assert 0.2 < np.mean(shows) < 0.9
    again = drawn_video(BOARD, seed=3, frames=60, condition="good", size=SIZE)
    assert all(np.array_equal(a, b) for a, b in zip(good.frames, again.frames))
    other = drawn_video(BOARD, seed=4, frames=60, condition="good", size=SIZE)
    assert not all(np.array_equal(a, b) for a, b in zip(good.frames, other.frames))


def test_dark_frames_hold_a_few_percent_of_the_light(good):
    dark = drawn_video(BOARD, seed=3, frames=60, condition="dark", size=SIZE)
    ratio = np.mean([d.mean() for d in dark.frames]) / np.mean([g.mean() for g in good.frames])
    assert 0.01 < ratio < 0.06
    assert [c is None for c in dark.corners] == [c is None for c in good.corners]


@pytest.mark.parametrize("motion", [(7.3, 0.0), (-4.0, 5.5), (0.2, -12.6)])
def test_a_smear_is_a_line_along_the_motion_centred_on_the_board(motion):
    kernel = _smear_kernel(np.array(motion))
    half = kernel.shape[0] // 2
    yy, xx = np.mgrid[:kernel.shape[0], :kernel.shape[1]]
    assert kernel.sum() == pytest.approx(1.0)
    assert (kernel * xx).sum() == pytest.approx(half, abs=1e-6) and (kernel * yy).sum() == pytest.approx(half, abs=1e-6)
    spread = np.sqrt((kernel * ((xx - half) ** 2 + (yy - half) ** 2)).sum())
    assert spread == pytest.approx(np.hypot(*motion) / np.sqrt(12), rel=0.1)  # a uniform line's spread
    assert _smear_kernel(np.array([0.3, 0.4])) is None


def test_only_a_shaken_board_is_smeared_and_the_video_says_how_far(good):
    assert set(good.smear) == {0.0}
    shaken = drawn_video(BOARD, seed=3, frames=60, condition="shake", size=SIZE)
    moving = [s for s, c in zip(shaken.smear, shaken.corners) if c is not None]
    assert max(moving) > 5 and all(s == 0 for s, c in zip(shaken.smear, shaken.corners) if c is None)
    # a smeared frame differs from the sharp one where the board is, not in the still background
    index = int(np.argmax(shaken.smear))
    difference = np.abs(shaken.frames[index].astype(int) - good.frames[index].astype(int))
    inside = np.zeros(difference.shape, bool)
    x0, y0 = np.floor(good.corners[index].min(axis=0)).astype(int)
    x1, y1 = np.ceil(good.corners[index].max(axis=0)).astype(int)
    inside[max(y0, 0):y1, max(x0, 0):x1] = True
    assert difference[inside].mean() > 5 * difference[~inside].mean()
