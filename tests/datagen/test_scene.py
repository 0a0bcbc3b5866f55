"""Scene sampling and camera conventions (plain numpy: no Blender needed)."""

import cv2
import numpy as np
import pytest

from blender_scenes.conversions import (
    K_from_blender_camera, blender_camera_from_K, blender_camera_matrix, board_pose_in_camera, cv_camera_from_blender,
)
from datagen.frames import blur_extent_px, frame_rng
from datagen.scene import SceneConfig, exposure_time_for, look_at, sample_board_look, sample_scene
from deepcharuco import BoardSpec, project_corners


@pytest.mark.parametrize("K, size", [
    (np.array([[277.1, 0, 159.5], [0, 277.1, 119.5], [0, 0, 1]]), (320, 240)),
    (np.array([[520.0, 0, 301.2], [0, 500.0, 222.9], [0, 0, 1]]), (640, 480)),
    (np.array([[300.0, 0, 100.3], [0, 290.0, 150.2], [0, 0, 1]]), (200, 300)),  # portrait, fx > fy
])
def test_blender_camera_round_trip(K, size):
    params = blender_camera_from_K(K, *size)
    np.testing.assert_allclose(K_from_blender_camera(params), K, atol=1e-9)


def test_blender_camera_rejects_what_it_cannot_render():
    with pytest.raises(ValueError, match="no skew"):
        blender_camera_from_K(np.array([[300.0, 2.0, 160], [0, 300, 120], [0, 0, 1]]), 320, 240)
    with pytest.raises(ValueError, match="fy <= fx"):
        blender_camera_from_K(np.array([[500.0, 0, 301.2], [0, 520.0, 222.9], [0, 0, 1]]), 640, 480)


def test_camera_matrix_conventions():
    world_from_camera = look_at(np.array([0.3, -0.5, 0.4]), np.zeros(3), roll_deg=20.0)
    np.testing.assert_allclose(cv_camera_from_blender(blender_camera_matrix(world_from_camera)), world_from_camera)
    # OpenCV's camera looks along +Z at the target; Blender's along its -Z.
    forward = world_from_camera[:3, 2]
    np.testing.assert_allclose(forward, -np.array([0.3, -0.5, 0.4]) / np.linalg.norm([0.3, -0.5, 0.4]), atol=1e-12)
    np.testing.assert_allclose(-blender_camera_matrix(world_from_camera)[:3, 2], forward, atol=1e-12)


def test_board_pose_in_camera_matches_world_projection():
    rng = np.random.default_rng(3)
    board = BoardSpec()
    spec = sample_scene(rng, board.size_m, SceneConfig.clean())
    rvec, tvec = board_pose_in_camera(spec.camera_matrix, spec.board_matrix)
    points = board.corner_points()
    world = points @ spec.board_matrix[:3, :3].T + spec.board_matrix[:3, 3]
    in_camera = (world - spec.camera_matrix[:3, 3]) @ spec.camera_matrix[:3, :3]  # world -> camera
    by_hand = in_camera[:, :2] / in_camera[:, 2:] * [spec.K[0, 0], spec.K[1, 1]] + spec.K[:2, 2]
    np.testing.assert_allclose(project_corners(board, rvec, tvec, spec.K), by_hand, atol=1e-9)


def test_board_rotation_is_rigid_when_the_board_faces_up():
    # Frame 163 of seed 0 draws a board facing within 8 degrees of straight up: its rotation was a
    # shear (R^T R off I by 0.14) that Blender rendered as a rotation, so labels drifted off the board.
    board = BoardSpec()
    for index in (163, 177, *range(40)):
        rotation = sample_scene(frame_rng(0, index), board.size_m).board_matrix[:3, :3]
        np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-9)
        assert np.linalg.det(rotation) == pytest.approx(1.0)
    assert abs(sample_scene(frame_rng(0, 163), board.size_m).board_matrix[2, 2]) > 0.99  # the case above


def test_rigid_refuses_what_blender_cannot_place():
    from blender_scenes.conversions import rigid

    with pytest.raises(ValueError, match="proper 3x3 rotation"):
        rigid(np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.14, 0.0, 1.0]]), np.zeros(3))
    with pytest.raises(ValueError, match="proper 3x3 rotation"):
        rigid(np.diag([1.0, 1.0, -1.0]), np.zeros(3))  # a reflection


def _spec_arrays(spec):
    return [spec.K, spec.trajectory, spec.board_matrix, *[s.matrix for s in spec.shapes], *[l.matrix for l in spec.lights]]


def test_sampling_is_a_function_of_the_seed():
    board = BoardSpec()
    a, b = (sample_scene(frame_rng(7, 12), board.size_m) for _ in range(2))
    c = sample_scene(frame_rng(7, 13), board.size_m)
    for x, y in zip(_spec_arrays(a), _spec_arrays(b)):
        np.testing.assert_array_equal(x, y)
    assert (a.render_seed, a.lux, a.tags) == (b.render_seed, b.lux, b.tags)
    assert a.render_seed != c.render_seed


def test_default_distribution_covers_the_paper_conditions():
    board = BoardSpec()
    specs = [sample_scene(frame_rng(0, i), board.size_m) for i in range(400)]
    lux = np.array([s.lux for s in specs])
    assert lux.min() < 1.0 and lux.max() > 300.0  # ~0.3 lux (paper's darkest) to ~700 lux
    negatives = sum(not s.board_present for s in specs)
    assert 15 <= negatives <= 70  # ~10 %
    assert all(s.distractors for s in specs if not s.board_present)  # negatives show a non-target board
    assert 0.35 < np.mean([s.shaken for s in specs]) < 0.65
    assert any(s.tags["shadow_caster"] for s in specs) and any(s.tags["spot"] for s in specs)
    assert any(s.tags["occluder"] for s in specs)
    assert {s.board_look.kind for s in specs} == {"matte", "glossy", "monitor"}
    # The board is in front of the camera and its centre usually in view.
    in_view = 0
    for spec in specs:
        rvec, tvec = board_pose_in_camera(spec.camera_matrix, spec.board_matrix)
        centre = project_corners(board, rvec, tvec, spec.K).mean(axis=0)
        assert (board.corner_points() @ cv2.Rodrigues(rvec)[0].T + tvec)[:, 2].min() > 0.029
        in_view += 0 <= centre[0] < spec.width and 0 <= centre[1] < spec.height
    assert in_view > 0.8 * len(specs)


def test_clean_config_is_clean():
    board = BoardSpec()
    for i in range(50):
        spec = sample_scene(frame_rng(1, i), board.size_m, SceneConfig.clean())
        assert spec.board_present and not spec.shaken and not spec.distractors
        assert spec.lux >= 300 and spec.board_look.kind == "matte"
        assert {s.role for s in spec.shapes} <= {"room", "clutter"}


def test_exposure_follows_light_until_the_frame_time():
    look = sample_board_look(np.random.default_rng(0), (1, 0, 0))
    sensor = SceneConfig().sensor
    times = [exposure_time_for(lux, look, sensor) for lux in (1000, 300, 30, 1, 0.3)]
    assert times == sorted(times)
    assert times[-1] == sensor.max_exposure_s and times[0] < 0.01


def test_blur_extent_grows_with_exposure():
    board = BoardSpec()
    bright = sample_scene(frame_rng(5, 0), board.size_m, SceneConfig(shake_p=1.0, lux=(900, 1000)))
    dark = sample_scene(frame_rng(5, 0), board.size_m, SceneConfig(shake_p=1.0, lux=(0.3, 0.31)))
    assert dark.exposure_s > 10 * bright.exposure_s
    assert blur_extent_px(board, dark) > 5 * blur_extent_px(board, bright) > 0
    still = sample_scene(frame_rng(5, 0), board.size_m, SceneConfig(shake_p=0.0))
    assert blur_extent_px(board, still) == 0.0
