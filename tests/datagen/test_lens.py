import cv2
import numpy as np
import pytest

from conftest import VIEW_POSES
from datagen.lens import (
    LensError, distort_image, distortion_displacement, distortion_maps, monotonic_k2, pixels_to_rays, wide_camera,
)
from deepcharuco import BoardSpec, OpenCVDetector
from deepcharuco.boards.synthetic import look_at_pose, render_board_view

K = np.array([[262.0, 0.0, 163.4], [0.0, 262.0, 117.1], [0.0, 0.0, 1.0]])
SIZE = (320, 240)
MODELS = {
    "barrel": np.array([-0.4, monotonic_k2(-0.4), 8e-4, -5e-4, 0.0]),
    "pincushion": np.array([0.1, monotonic_k2(0.1), 0.0, 0.0, 0.0]),
    "rational": np.array([-0.3, 0.1, 1e-3, 1e-3, 0.02, 0.05, 0.01, 0.001]),
    "thin prism": np.array([-0.2, 0.05, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1e-3, -1e-3, 5e-4, 2e-4]),
}


@pytest.mark.parametrize("name", list(MODELS))
def test_rays_project_back_to_their_pixels(name):
    """pixels_to_rays inverts OpenCV's model: cv2.projectPoints of the ray gives the pixel back."""
    dist = MODELS[name]
    pixels = np.random.default_rng(0).uniform((-0.5, -0.5), (SIZE[0] - 0.5, SIZE[1] - 0.5), size=(500, 2))
    rays = pixels_to_rays(pixels, K, dist)
    back, _ = cv2.projectPoints(np.column_stack([rays, np.ones(len(rays))]), np.zeros(3), np.zeros(3), K, dist)
    assert np.abs(back.reshape(-1, 2) - pixels).max() < 1e-6


def test_folding_model_is_refused():
    # r (1 - 0.4 r^2) peaks at r = 0.91 (distorted 0.61): the image corners (0.76) lie beyond the fold.
    with pytest.raises(LensError, match="folds inside the image"):
        wide_camera(K, np.array([-0.4, 0.0, 0.0, 0.0, 0.0]), SIZE)
    with pytest.raises(LensError, match="4, 5, 8 or 12"):
        pixels_to_rays(np.zeros((1, 2)), K, np.zeros(3))


@pytest.mark.parametrize("name", ["barrel", "pincushion"])
def test_wide_camera_covers_every_output_pixel(name):
    dist = MODELS[name]
    K_wide, (width, height) = wide_camera(K, dist, SIZE)
    map_x, map_y = distortion_maps(K, dist, SIZE, K_wide, supersample=2)
    assert map_x.shape == (2 * SIZE[1], 2 * SIZE[0])
    assert map_x.min() >= 0 and map_y.min() >= 0 and map_x.max() <= width - 1 and map_y.max() <= height - 1
    # Barrel: the render must see farther out than the image (wider); pincushion: less far.
    assert (width > SIZE[0] + 20) == (name == "barrel")


def test_distorted_view_puts_corners_where_project_points_does():
    """OpenCV finds the corners of a distorted synthetic view where cv2.projectPoints (K, dist) puts them,
    and nowhere near the undistorted projection."""
    board = BoardSpec()
    dist = MODELS["barrel"]
    K_wide, wide_size = wide_camera(K, dist, SIZE, scale=2.0)
    maps = distortion_maps(K, dist, SIZE, K_wide)
    detector = OpenCVDetector(board)
    errors, shifts = [], []
    for pose in VIEW_POSES[:3]:
        rvec, tvec = look_at_pose(board, **{**pose, "offset": (0.06, 0.04)})
        image = distort_image(render_board_view(board, K_wide, rvec, tvec, wide_size, supersample=2), K, dist, SIZE,
                              K_wide, maps=maps)
        detection = detector.detect(image)
        assert len(detection) >= 12
        truth, _ = cv2.projectPoints(board.corner_points()[detection.ids], rvec, tvec, K, dist)
        pinhole, _ = cv2.projectPoints(board.corner_points()[detection.ids], rvec, tvec, K, None)
        errors.append(np.linalg.norm(detection.corners - truth.reshape(-1, 2), axis=1))
        shifts.append(np.linalg.norm(detection.corners - pinhole.reshape(-1, 2), axis=1))
    assert np.median(np.concatenate(errors)) < 0.15
    assert np.median(np.concatenate(shifts)) > 1.0  # ~10x the error above: the distortion is really there


def test_distortion_displacement_is_zero_at_the_centre_and_large_at_the_corners():
    dist = MODELS["barrel"]
    shift = distortion_displacement(K, dist, np.array([[K[0, 2], K[1, 2]], [0.0, 0.0], [319.0, 239.0]]))
    assert np.linalg.norm(shift[0]) < 1e-3
    # Barrel: the corners are pulled towards the centre (the ray's pinhole image lies farther out).
    assert shift[1, 0] > 20 and shift[1, 1] > 15 and shift[2, 0] < -20 and shift[2, 1] < -15
