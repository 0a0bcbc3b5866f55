"""Rigs of fisheye (~180 degree) lenses: the bundle adjustment's fisheye projection against OpenCV's, exact projections
through known fisheye and mixed rigs, a drawn fisheye rig through the command, and the model's refusals."""

import tomllib

import cv2
import numpy as np
import pytest

from deepcharuco import Camera, read_camera, write_camera
from deepcharuco.calibration.rig import calibrate_rig
from deepcharuco.calibration.rig_model import (RigView, camera_from_vector, intrinsic_vector, project,
                                               rotation_angle_deg)
from deepcharuco.cli.calibrate import main
from evaluate.calibration.fisheye_views import (FISHEYE_BOARD, drawn_fisheye_rig, fisheye_board_poses,
                                                fisheye_cameras, visible_corners)

SIZE = (1024, 768)
LENS = ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")


def test_the_fisheye_projection_is_opencvs_out_to_90_degrees():
    rng = np.random.default_rng(0)
    for dist in ([0.02, -0.01, 0.003, -0.0005], [-0.05, 0.02, -0.004, 0.001]):
        camera = Camera(np.array([[240.0, 0, 518], [0, 241, 380], [0, 0, 1]]), np.array(dist), SIZE, model="fisheye")
        theta, phi = np.radians(rng.uniform(0, 89.9, 3000)), rng.uniform(0, 2 * np.pi, 3000)
        points = np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
        points = np.vstack([points * rng.uniform(0.1, 5.0, (3000, 1)), [[0, 0, 1.0], [1e-11, -1e-11, 2.0]]])
        ours = project(points, np.tile(intrinsic_vector(camera), (len(points), 1)), np.ones(len(points), bool))
        theirs = camera.project(points, np.zeros(3), np.zeros(3))
        scale = np.maximum(np.linalg.norm(theirs - camera.K[:2, 2], axis=1), 1.0)
        assert (np.linalg.norm(ours - theirs, axis=1) / scale).max() < 1e-9
        again = camera_from_vector(intrinsic_vector(camera), SIZE, 5, "fisheye")
        assert again.model == "fisheye" and np.array_equal(again.dist, camera.dist) and np.array_equal(again.K, camera.K)


def exact_views(cameras, rotations, translations, board_r, board_t, noise, seed=0):
    """Every camera's view of every board pose: its visible corners (15 px inside the frame; a pinhole camera's
    within 40 degrees of its axis, where its distortion model holds) through its own model, plus Gaussian noise of
    ``noise`` px."""
    rng = np.random.default_rng(seed)
    points = FISHEYE_BOARD.object_points()
    views = []
    for c, (camera, R, t) in enumerate(zip(cameras, rotations, translations)):
        for n, (R_b, t_b) in enumerate(zip(board_r, board_t)):
            R_c, t_c = R @ R_b, R @ t_b + t
            ids = visible_corners(FISHEYE_BOARD, camera, R_c, t_c, border=15)
            if camera.model == "pinhole":
                seen = points[ids] @ R_c.T + t_c
                ids = ids[np.hypot(seen[:, 0], seen[:, 1]) < np.tan(np.radians(40)) * seen[:, 2]]
            if len(ids) >= 6:
                pixels = camera.project(points[ids], cv2.Rodrigues(R_c)[0], t_c)
                views.append(RigView(c, n, ids, pixels + rng.normal(0, noise, pixels.shape)))
    return views


def nudged(camera: Camera) -> Camera:
    """Starting intrinsics as a camera's own calibration leaves them: f 0.3-0.5 % and cx 2 px off, distortion 10 %."""
    K = camera.K.copy()
    K[0, 0] *= 1.005
    K[1, 1] *= 0.997
    K[0, 2] += 2
    return Camera(K, camera.dist * 0.9, camera.image_size, model=camera.model)


def fisheye_rig(seed, instants):
    rng = np.random.default_rng(seed)
    cameras, rotations, translations = fisheye_cameras(rng, 3, SIZE)
    centres = np.stack([-R.T @ t for R, t in zip(rotations, translations)])
    board_r, board_t = fisheye_board_poses(rng, FISHEYE_BOARD, centres.mean(0), instants)
    return cameras, rotations, translations, centres, board_r, board_t


def test_a_fisheye_rig_comes_back_within_its_deviations():
    """Three 180 degree lenses, 24 instants, corners exact + 0.1 px noise out to the image circle's rim. Measured
    (2026-11-27): rotations within 0.012 degree, centres within 0.3 mm per metre of baseline, every lens parameter
    within 2.1 of its deviation; asserted at the issue's targets and 3.5 deviations."""
    cameras, rotations, translations, centres, board_r, board_t = fisheye_rig(seed=3, instants=24)
    views = exact_views(cameras, rotations, translations, board_r, board_t, noise=0.1)
    result = calibrate_rig(views, FISHEYE_BOARD, [nudged(c) for c in cameras], ["a", "b", "c"], ["k1 k2 k3 k4"] * 3)
    assert 0.12 < result.rms < 0.16 and not result.dropped
    baseline = max(np.linalg.norm(a - b) for a in centres for b in centres)
    for c, camera in enumerate(cameras):
        solved = result.cameras[c]
        assert solved.model == "fisheye" and solved.dist.shape == (4,)
        errors = dict(zip(LENS, [*(solved.K - camera.K)[[0, 1, 0, 1], [0, 1, 2, 2]], *(solved.dist - camera.dist)]))
        ratios = {name: error / result.std[c][name] for name, error in errors.items()}
        assert max(abs(r) for r in ratios.values()) < 3.5, (c, ratios)
        if c:
            assert rotation_angle_deg(result.rotations[c] @ rotations[c].T) < 0.1
            assert 1000 * np.linalg.norm(result.centre(c) - centres[c]) / baseline < 2.0


def test_a_rig_mixing_fisheye_and_rational_cameras_comes_back_exactly():
    """A rational-model camera of ~80 degrees between two 180 degree lenses, exact corners, every intrinsic
    free: each camera's own model recovers the truth. Measured (2026-11-27): K to 2e-7 px, distortion to 1e-8,
    poses to 1e-9; asserted at ~5x."""
    cameras, rotations, translations, _, board_r, board_t = fisheye_rig(seed=4, instants=24)
    K = np.array([[600.0, 0, 515], [0, 602, 380], [0, 0, 1]])
    cameras[0] = Camera(K, np.array([-0.25, 0.08, 1e-3, -5e-4, -0.01, 0.02, 0.01, 0.002]), SIZE)
    views = exact_views(cameras, rotations, translations, board_r, board_t, noise=0.0)
    assert sum(v.camera == 0 for v in views) >= 8
    terms = ["k1 k2 p1 p2 k3 k4 k5 k6", "k1 k2 k3 k4", "k1 k2 k3 k4"]
    result = calibrate_rig(views, FISHEYE_BOARD, [nudged(c) for c in cameras], ["a", "b", "c"], terms)
    assert [c.model for c in result.cameras] == ["pinhole", "fisheye", "fisheye"] and result.rms < 1e-6
    for c, camera in enumerate(cameras):
        assert result.cameras[c].dist.shape == camera.dist.shape
        assert np.abs(result.cameras[c].K - camera.K).max() < 1e-5, c
        assert np.abs(result.cameras[c].dist - camera.dist).max() < 1e-6, c
        assert np.abs(result.rotations[c] - rotations[c]).max() < 1e-8 and np.abs(
            result.translations[c] - translations[c]).max() < 1e-8, c


# ----------------------------------------------------------------------------------------- the command
@pytest.fixture(scope="module")
def drawn(tmp_path_factory):
    """A small drawn fisheye rig (800 x 600, 12 instants, OpenCV's corners find it) as three folders of frames."""
    truth, _ = drawn_fisheye_rig(seed=5, instants=12, size=(800, 600), supersample=1)
    root = tmp_path_factory.mktemp("fisheye_rig")
    return truth, truth.save_frames(root), FISHEYE_BOARD.save(root / "board.yaml")


def test_the_command_calibrates_a_drawn_fisheye_rig(tmp_path, drawn, capsys):
    """Measured (2026-11-27): rotations within 0.08 degree, centres within 2.8 mm per metre of baseline (12 instants,
    frames drawn without supersampling), fx within 0.35 %; asserted at ~2x."""
    truth, folders, board = drawn
    out = tmp_path / "rig"
    assert main([*map(str, folders), "--board", str(board), "--detector", "opencv", "--model", "fisheye", "--out",
                 str(out), "--quiet"]) == 0
    assert "3 cameras" in capsys.readouterr().out
    toml = tomllib.loads((out / "rig.toml").read_text())
    centres = [-R.T @ t for R, t in zip(truth.rotations, truth.translations)]
    for c in range(3):
        camera = read_camera(out / f"cam{c}.yaml")
        assert camera.model == "fisheye" and abs(camera.K[0, 0] / truth.cameras[c].K[0, 0] - 1) < 0.007
        storage = cv2.FileStorage(str(out / f"cam{c}.yaml"), cv2.FILE_STORAGE_READ)
        R, t = storage.getNode("rotation_matrix").mat(), storage.getNode("translation_vector").mat().ravel()
        storage.release()
        assert rotation_angle_deg(R @ truth.rotations[c].T) < 0.16
        assert 1000 * np.linalg.norm(-R.T @ t - centres[c]) / truth.baseline < 6.0
        assert toml[f"cam_{c}"]["fisheye"] is True and len(toml[f"cam_{c}"]["distortions"]) == 4
    assert "fisheye: " in (out / "rig_report.html").read_text()


def test_every_camera_given_with_another_model_is_refused_before_any_work(tmp_path, drawn, capsys):
    truth, folders, board = drawn
    files = [write_camera(tmp_path / f"cam{c}.yaml", truth.cameras[c]) for c in range(2)]
    out = tmp_path / "rig"
    code = main([str(folders[0]), str(folders[1]), "--board", str(board), "--detector", "opencv", "--model",
                 "rational", "--camera", str(files[0]), "--camera", str(files[1]), "--out", str(out), "--quiet"])
    error = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(error) == 1
    assert "--model rational is the model of the cameras the rig solves" in error[0] and "is a fisheye camera" in error[0]
    assert not (out / "rig.toml").exists()
    with pytest.raises(SystemExit) as stop:
        main([str(folders[0]), str(folders[1]), "--model", "fisheye", "--all-terms"])
    assert stop.value.code == 2 and "--all-terms is for the pinhole and rational models" in capsys.readouterr().err


def test_one_fisheye_camera_leaves_out_the_corners_at_its_rim():
    """A 180 degree lens whose corners beyond 84 degrees off the axis are 2 px off (a detector's at the image
    circle's rim): cv2.fisheye.calibrate failed on them ("norm_u1 > 0", 2026-11-27); left out beyond 80 degrees, fx
    comes within 0.12 % (asserted 0.4 %)."""
    from deepcharuco.calibration.intrinsics import calibrate
    from deepcharuco.calibration.views import FrameDetection

    rng = np.random.default_rng(6)
    (camera,), _, _ = fisheye_cameras(rng, 1, SIZE)
    board_r, board_t = fisheye_board_poses(rng, FISHEYE_BOARD, np.zeros(3), 30)
    points = FISHEYE_BOARD.object_points()
    frames = []
    for n, (R, t) in enumerate(zip(board_r, board_t)):
        ids = visible_corners(FISHEYE_BOARD, camera, R, t, border=3)
        pixels = camera.project(points[ids], cv2.Rodrigues(R)[0], t) + rng.normal(0, 0.1, (len(ids), 2))
        seen = points[ids] @ R.T + t
        rim = np.degrees(np.arctan2(np.hypot(seen[:, 0], seen[:, 1]), seen[:, 2])) > 84
        pixels[rim] += rng.normal(0, 2.0, (rim.sum(), 2))
        frames.append(FrameDetection(n, str(n), ids, pixels, 1.0))
    result = calibrate(frames, FISHEYE_BOARD, SIZE, "fisheye")
    assert abs(result.camera.K[0, 0] / camera.K[0, 0] - 1) < 0.004 and result.rms < 0.2
    assert sum("beyond 80 degrees off the lens's axis unused" in d.reason for d in result.decisions) >= 5


def test_a_narrow_lens_fisheye_solve_keeps_its_corners():
    """A first fisheye solve of a ~63 degree lens (k1..k4 as `calibrate --model fisheye` found them on 14 drawn views)
    turns theta_d down past its corners and below 0 by 80 degrees: every corner counted as beyond the rim, no view
    left, and OpenCV's assertion as the error. The limit is where theta_d stops growing: the corners stay."""
    from deepcharuco.calibration.solve import Solution, beyond_fisheye_reach

    K = np.array([[520.0, 0.0, 322.3], [0.0, 518.0, 236.8], [0.0, 0.0, 1.0]])
    solution = Solution(K=K, dist=np.array([0.2065, 0.1041, 0.1186, -0.5966]), rvecs=np.zeros((0, 3)),
                        tvecs=np.zeros((0, 3)), std={})
    corners = np.array([[322.3, 236.8], [0.0, 0.0], [639.0, 479.0], [0.0, 479.0]])  # the axis and the image corners
    assert not beyond_fisheye_reach([corners], solution)[0].any()
    far = np.array([[322.3 + 520.0 * 50, 236.8]])  # 50 units off the axis on the image plane: past any turn
    assert beyond_fisheye_reach([far], solution)[0].all()
    wide = Solution(K=K, dist=np.zeros(4), rvecs=np.zeros((0, 3)), tvecs=np.zeros((0, 3)), std={})
    limit = np.radians(80.0)  # an equidistant lens: theta_d = theta grows to 80 degrees, the limit as before
    at = np.array([[322.3 + 520.0 * limit * 0.999, 236.8], [322.3 + 520.0 * limit * 1.001, 236.8]])
    assert beyond_fisheye_reach([at], wide)[0].tolist() == [False, True]
