"""Acceptance: the texture -> board map is exact, as OpenCV's detector sees it."""

import cv2
import numpy as np
import pytest

from deepcharuco import BoardSpec, OpenCVDetector
from deepcharuco.boards.synthetic import look_at_pose, texture_homography


@pytest.mark.parametrize(
    "board, px_per_m, margin",
    [
        (BoardSpec(), 3001.7, 0.01),  # edges between pixels
        (BoardSpec(7, 5, 0.04, 0.03, "DICT_6X6_250"), 2203.3, 0.0),
        (BoardSpec(6, 6, 0.03, 0.022, "DICT_4X4_50", legacy=True), 4117.0, 0.005),
    ],
)
def test_warped_texture_corners_match_board_geometry(board, px_per_m, margin):
    texture = board.render_texture(px_per_m, margin)
    K = np.array([[300.0, 0, 319.5], [0, 300.0, 239.5], [0, 0, 1]])
    detector = OpenCVDetector(board, refine="subpix")
    errors = []
    for tilt_x, tilt_y, roll in [(0, 0, 0), (25, -15, 10), (-30, 20, 135)]:
        distance = 1.3 * max(board.size_m) * 300.0 / 240.0
        rvec, tvec = look_at_pose(board, distance, tilt_x, tilt_y, roll)
        # Warp at 4x and box-filter down: the texture -> image homography is the only geometry used.
        H = texture_homography(texture, K, rvec, tvec)
        to_fine = np.array([[4.0, 0, 1.5], [0, 4.0, 1.5], [0, 0, 1]])
        fine = cv2.warpPerspective(texture.image, to_fine @ H, (2560, 1920), flags=cv2.INTER_LINEAR,
                                   borderValue=100)
        image = cv2.resize(fine, (640, 480), interpolation=cv2.INTER_AREA)
        detection = detector.detect(image)
        assert len(detection) >= 0.8 * board.num_corners
        # BoardSpec geometry -> texture pixels (the documented map) -> image through the same H.
        tex_points = texture.board_to_texture(board.corner_points()[detection.ids])
        projected = cv2.perspectiveTransform(tex_points.reshape(-1, 1, 2), H).reshape(-1, 2)
        errors.append(np.linalg.norm(detection.corners - projected, axis=1))
    errors = np.concatenate(errors)
    assert np.median(errors) < 0.1, f"median {np.median(errors):.3f} px"
    assert np.percentile(errors, 90) < 0.3
