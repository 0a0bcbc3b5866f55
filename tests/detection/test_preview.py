"""The half-size preview of small images: kept only when it found the whole board in view, refined at full
resolution; a partial or too-small preview leaves the result to the full image, exactly as without it."""

import cv2
import numpy as np
import pytest
import torch

from conftest import network_widths
from deepcharuco import BoardSpec, Camera, Detector, project_corners
from deepcharuco.boards.synthetic import look_at_pose, render_board_view

CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 0.01)
BOARD = BoardSpec()  # the shipped weights' board: the preview serves its own decoding


@pytest.fixture(scope="module")
def camera() -> Camera:
    return Camera.from_fov(320, 240, hfov_deg=60.0)


def view(camera: Camera, distance: float, offset=(0.0, 0.0)):
    rvec, tvec = look_at_pose(BOARD, distance, tilt_x_deg=20, tilt_y_deg=-15, roll_deg=8, offset=offset)
    image = render_board_view(BOARD, camera.K, rvec, tvec, camera.image_size)
    return image, project_corners(BOARD, rvec, tvec, camera.K)


def test_a_whole_board_is_found_in_the_preview_and_refined_at_full_resolution(camera):
    image, truth = view(camera, distance=0.30)  # the whole board, squares ~30 px
    previewed, widths = network_widths(Detector(), image)
    assert widths == [160]  # one network pass, at half size
    full, full_widths = network_widths(Detector(preview=False), image)
    assert full_widths == [320]
    assert np.array_equal(np.sort(previewed.ids), np.sort(full.ids)) and len(full.ids) == BOARD.num_corners
    error = np.linalg.norm(previewed.corners - truth[previewed.ids], axis=1)
    full_error = np.linalg.norm(full.corners - truth[full.ids], axis=1)
    assert np.median(error) < 0.3 and np.median(error) < np.median(full_error) + 0.1


def test_a_preview_costs_one_refinenet_pass_at_full_resolution(camera):
    image, truth = view(camera, distance=0.30)
    detector = Detector()
    batches, run = [], detector.runner.refinenet

    def recording(patches):
        batches.append(len(patches))
        return run(patches)

    detector.runner.refinenet = recording
    found = detector.detect(image)
    assert batches == [BOARD.num_corners]  # cornerSubPix centred them in the preview, RefineNet once
    assert np.max(np.linalg.norm(found.corners - truth[found.ids], axis=1)) < 0.5


def test_a_preview_corner_is_nudged_onto_the_corner_at_most_one_and_a_half_pixels():
    from deepcharuco.detection.levels import PREVIEW_MAX_NUDGE_PX, nudged

    # A chessboard X-junction at (30.3, 20.6): dark top-left and bottom-right quadrants, drawn 8x oversampled.
    size, scale, corner = (40, 60), 8, np.array([30.3, 20.6])
    ys, xs = np.mgrid[0:size[0] * scale, 0:size[1] * scale]
    x, y = (xs + 0.5) / scale - 0.5, (ys + 0.5) / scale - 0.5
    fine = np.where((x < corner[0]) == (y < corner[1]), 40.0, 210.0)
    gray = fine.reshape(size[0], scale, size[1], scale).mean(axis=(1, 3)).astype(np.uint8)
    start = np.array([[30.0, 21.0]], np.float32)  # the point head's pixel
    assert np.linalg.norm(nudged(gray, start)[0] - corner) < 0.1
    off = np.array([[32.0, 22.0]], np.float32)  # 2.2 px off: cornerSubPix reaches the corner, too far a move
    assert np.linalg.norm(cv2.cornerSubPix(gray, off[:, None].copy(), (2, 2), (-1, -1), CRITERIA).ravel() - corner) < 0.1
    assert PREVIEW_MAX_NUDGE_PX < 2.2 and np.array_equal(nudged(gray, off), off)


def test_a_partial_or_small_preview_leaves_the_full_image_to_decide(camera):
    cut, _ = view(camera, distance=0.25, offset=(0.10, 0.0))  # the board runs off the right edge: 14 of 16 in view
    far, _ = view(camera, distance=0.55)  # squares ~16 px: 8 px in the preview, too small to trust
    for image in (cut, far):
        previewed, widths = network_widths(Detector(), image)
        full = Detector(preview=False).detect(image)
        assert widths == [160, 320]
        assert np.array_equal(previewed.ids, full.ids) and np.array_equal(previewed.corners, full.corners)
        assert len(full.ids) >= 6


def test_no_preview_for_images_larger_than_the_working_size():
    blank = np.full((480, 640), 128, np.uint8)  # each level up to 640 px searched whole once, nothing finer
    assert network_widths(Detector(), blank)[1] == [320, 640]
    assert network_widths(Detector(), blank[:240, :320])[1] == [160, 320]
    assert network_widths(Detector(preview=False), blank[:240, :320])[1] == [320]


def test_a_board_read_by_its_markers_is_not_previewed(camera):
    other = BoardSpec(squares_x=7, squares_y=5, square_length=0.04, marker_length=0.03, dictionary="DICT_6X6_250")
    rvec, tvec = look_at_pose(other, 0.33, tilt_x_deg=15, tilt_y_deg=-10, roll_deg=5)  # squares ~32 px
    image = render_board_view(other, camera.K, rvec, tvec, camera.image_size)
    found, widths = network_widths(Detector(board=other), image)
    assert widths == [320] and len(found.ids) == other.num_corners
    assert not Detector(geometry="none").preview and Detector(geometry="filter").preview


def test_refinenet_may_move_a_corner_three_pixels_no_farther():
    from deepcharuco.networks.refinenet import GRID

    detector = Detector()
    gray = np.full((60, 60), 128, np.uint8)
    pixels = np.array([[20.0, 20.0], [40.0, 30.0]], np.float32)

    def peaked_at(cell_x: int, cell_y: int):
        def refinenet(patches):
            logits = np.full((len(patches), GRID * GRID), -20.0, np.float32)
            logits[:, cell_y * GRID + cell_x] = 20.0
            return torch.from_numpy(logits)
        return refinenet

    detector.runner.refinenet = peaked_at(36, 36)  # 7.5 + 36.5 / 8 = 12.06: 0.06 px from the pixel, kept
    assert np.allclose(detector._refine(gray, pixels), pixels + 0.0625, atol=1e-4)
    detector.runner.refinenet = peaked_at(0, 0)  # 7.56: 6.3 px away, onto noise: the pixel stays
    assert np.array_equal(detector._refine(gray, pixels), pixels)
    # Corners scaled up from a reduced level may be that far off: RefineNet's answer stands there.
    assert np.allclose(detector._refine(gray, pixels, window_scale=2.0), pixels - 4.4375, atol=1e-4)
