"""Rig calibration (deepcharuco.calibration.rig, calibrate with several sources): exact projections through known rigs, drawn
views through the CLI, and the refusals of bad input."""

import tomllib

import cv2
import numpy as np
import pytest

from conftest import assert_same_but_rounding, needs_bpy
from deepcharuco import BoardSpec, Camera, read_camera, write_camera
from deepcharuco.calibration.bundle import corner_weights
from deepcharuco.calibration.rig import calibrate_rig
from deepcharuco.calibration.rig_model import (RigError, RigView, intrinsic_vector, project, rotation_angle_deg,
                                               rotations_from_vectors)
from deepcharuco.cli.calibrate import main
from deepcharuco.cli.calibrate_rig import board_origin
from evaluate.calibration.rig_views import RIG_BOARD, board_poses, drawn_rig, rig_cameras

SIZE = (640, 480)


def exact_views(seed: int, instants: int = 30, noise: float = 0.1, cameras: int = 3, seen=None):
    """(cameras, rotations, translations, views): the corners each camera sees, projected exactly plus Gaussian
    noise of ``noise`` px; ``seen(camera, instant)`` False leaves a view out."""
    rng = np.random.default_rng(seed)
    intrinsics, rotations, translations, target = rig_cameras(rng, cameras, SIZE)
    board_r, board_t = board_poses(rng, RIG_BOARD, target, instants)
    points = RIG_BOARD.object_points()
    views = []
    for c, (camera, R, t) in enumerate(zip(intrinsics, rotations, translations)):
        for n in range(instants):
            if seen is not None and not seen(c, n):
                continue
            R_c, t_c = R @ board_r[n], R @ board_t[n] + t
            pixels = camera.project(points, cv2.Rodrigues(R_c)[0], t_c)
            inside = ((pixels > 15) & (pixels < np.array(SIZE) - 15)).all(1) & ((points @ R_c.T + t_c)[:, 2] > 0)
            if inside.sum() >= 6:
                views.append(RigView(c, n, np.flatnonzero(inside), pixels[inside] + rng.normal(0, noise, (inside.sum(), 2))))
    return intrinsics, rotations, translations, views


def perturbed(cameras):
    """Starting intrinsics 1-2 % and 4 px off, the distortion 20 % off."""
    out = []
    for camera in cameras:
        K = camera.K.copy()
        K[0, 0] *= 1.02
        K[1, 1] *= 0.99
        K[0, 2] += 4
        out.append(Camera(K, camera.dist * 0.8, camera.image_size))
    return out


def test_projection_is_opencvs_for_the_rational_model():
    camera = Camera(np.array([[500.0, 0, 310], [0, 505, 250], [0, 0, 1]]),
                    np.array([-0.3, 0.1, 1e-3, -2e-3, 0.02, 0.05, -0.01, 0.003]), SIZE)
    points = np.random.default_rng(0).uniform([-0.5, -0.4, 1.0], [0.5, 0.4, 2.0], (50, 3))
    ours = project(points, np.tile(intrinsic_vector(camera), (len(points), 1)))
    assert np.abs(ours - camera.project(points, np.zeros(3), np.zeros(3))).max() < 1e-9
    rvecs = np.array([[0.0, 0, 0], [1e-14, 0, 0], [0.3, -1.2, 2.0]])
    assert np.allclose(rotations_from_vectors(rvecs), [cv2.Rodrigues(r)[0] for r in rvecs], atol=1e-12)


def test_bundle_adjustment_recovers_the_rig_and_its_deviations_are_honest():
    cameras, rotations, translations, views = exact_views(seed=3)
    result = calibrate_rig(views, RIG_BOARD, perturbed(cameras), ["a", "b", "c"], ["k1 k2 k3"] * 3)
    assert 0.12 < result.rms < 0.16  # 0.1 px per axis: sqrt(2) x 0.1 in 2-D, less what the fit absorbs
    assert not result.dropped
    for c, camera in enumerate(cameras):
        # Every intrinsic solved, within 3 of its deviations (seed 3: at most 1.6) and fx fy cx cy within 0.6 px
        # (at most 0.2 px, 2026-11-27).
        found, true = result.cameras[c], camera
        errors = {"fx": found.K[0, 0] - true.K[0, 0], "fy": found.K[1, 1] - true.K[1, 1],
                  "cx": found.K[0, 2] - true.K[0, 2], "cy": found.K[1, 2] - true.K[1, 2],
                  "k1": found.dist[0] - true.dist[0], "k2": found.dist[1] - true.dist[1], "k3": found.dist[4] - true.dist[4]}
        assert set(result.std[c]) >= set(errors)
        assert all(abs(error) < 3 * result.std[c][name] for name, error in errors.items()), (c, errors)
        assert max(abs(errors[name]) for name in ("fx", "fy", "cx", "cy")) < 0.6, (c, errors)
        if c:
            assert rotation_angle_deg(result.rotations[c] @ rotations[c].T) < 4 * result.std[c]["rotation_deg"] + 1e-3
            error = result.translations[c] - translations[c]
            deviation = np.array([result.std[c][k] for k in ("tx", "ty", "tz")])
            assert np.all(np.abs(error) < 4 * deviation) and np.linalg.norm(error) < 0.003
    assert result.shared[(0, 1)] >= 20
    # The same rig in the board's frame at instant 0 projects every corner where camera 0's frame did.
    rvec, tvec = result.board_poses[(0, 0)]
    moved = result.reframed(rotations_from_vectors(rvec)[0], tvec)
    for c in range(3):
        view = next(v for v in result.views if v.camera == c and v.instant == 0)
        points = RIG_BOARD.object_points()[view.ids]
        before = result.cameras[c].project(points @ rotations_from_vectors(rvec)[0].T + tvec,
                                           cv2.Rodrigues(result.rotations[c])[0], result.translations[c])
        after = result.cameras[c].project(points, cv2.Rodrigues(moved.rotations[c])[0], moved.translations[c])
        assert np.abs(before - after).max() < 1e-6


def test_bundle_adjustment_recovers_the_exact_rig_without_noise():
    """Exact corners (no noise), a start 1-2 % and 4 px off: every intrinsic, distortion term, camera pose and board
    pose comes back to the truth. Measured (2026-11-27, 12 instants): K to 6e-8 px, distortion to 1.1e-9, rotation
    matrices to 1.6e-10, translations to 1.5e-10 m, RMS 7e-10 px; asserted at ~3x that (with 30 instants the solver
    stops 10x nearer still)."""
    seed, instants = 3, 12
    cameras, rotations, translations, views = exact_views(seed=seed, instants=instants, noise=0.0)
    rng = np.random.default_rng(seed)  # the board poses exact_views drew, drawn again (camera 0 is the rig's frame)
    target = rig_cameras(rng, 3, SIZE)[3]
    board_r, board_t = board_poses(rng, RIG_BOARD, target, instants)
    result = calibrate_rig(views, RIG_BOARD, perturbed(cameras), ["a", "b", "c"], ["k1 k2 k3"] * 3)
    assert result.rms < 2e-9 and not result.dropped
    for c, camera in enumerate(cameras):
        assert np.abs(result.cameras[c].K - camera.K).max() < 2e-7, c  # fx fy cx cy, px
        assert np.abs(result.cameras[c].dist - camera.dist).max() < 3e-9, c  # k1 k2 and k3 (0), p1 p2 held at 0
        assert np.abs(result.rotations[c] - rotations[c]).max() < 5e-10 and np.abs(
            result.translations[c] - translations[c]).max() < 5e-10, c
    assert len(result.board_poses) == instants
    for (instant, _), (rvec, tvec) in result.board_poses.items():
        assert np.abs(rotations_from_vectors(rvec)[0] - board_r[instant]).max() < 5e-10
        assert np.abs(tvec - board_t[instant]).max() < 5e-10


def test_corners_weigh_by_their_covariances_and_their_views_excess():
    cameras, _, _, views = exact_views(seed=6, instants=8)
    alike = [RigView(v.camera, v.instant, v.ids, v.corners, covariances=np.tile(0.04 * np.eye(2), (len(v.ids), 1, 1)))
             for v in views]
    assert all(np.allclose(w, np.eye(2)) for w in corner_weights(alike))  # equal covariances: the unweighted solve
    # A view whose residuals spread more than its corners' covariances say gets that excess and weighs less.
    rng = np.random.default_rng(0)
    residuals = [rng.normal(0, 0.5 if k == 0 else 0.1, (len(v.ids), 2)) for k, v in enumerate(alike)]
    weights = corner_weights(alike, residuals)
    assert np.trace(weights[0].mean(0)) < 0.5 * np.trace(weights[1].mean(0))


def test_weighing_corners_by_their_covariances_places_the_cameras_better():
    # Half the corners of every view are 10 x noisier (a blurred half of the board), and their covariances say so:
    # weighed by them the rig comes out nearer the truth than with every corner alike.
    errors = {True: [], False: []}
    for seed in (7, 8):
        cameras, rotations, translations, views = exact_views(seed=seed, instants=16, noise=0.0)
        rng = np.random.default_rng(seed)
        noisy = []
        for v in views:
            sigma = np.where(np.arange(len(v.ids)) % 2 == 0, 0.05, 0.5)
            covariances = sigma[:, None, None] ** 2 * np.eye(2)
            noisy.append(RigView(v.camera, v.instant, v.ids, v.corners + rng.normal(0, 1, v.corners.shape) * sigma[:, None],
                                 covariances=covariances))
        for weigh in (True, False):
            result = calibrate_rig(noisy, RIG_BOARD, perturbed(cameras), ["a", "b", "c"], ["k1 k2 k3"] * 3,
                                   weigh_corners=weigh)
            assert result.corners_weighed == weigh
            errors[weigh].append(max(
                [rotation_angle_deg(result.rotations[c] @ rotations[c].T) / 0.01 for c in (1, 2)]
                + [np.linalg.norm(result.translations[c] - translations[c]) / 0.001 for c in (1, 2)]
                + [abs(result.cameras[c].K[0, 0] / cameras[c].K[0, 0] - 1) / 1e-4 for c in range(3)]))
    assert sum(errors[True]) < 0.5 * sum(errors[False]), errors  # 0.25 x when written


def test_a_camera_is_placed_through_another_when_it_never_shares_a_view_with_the_first():
    # Camera 2 sees the board only at instants camera 0 does not: it is linked through camera 1.
    cameras, rotations, translations, views = exact_views(seed=4, seen=lambda c, n: not (c == 0 and n % 2) and
                                                          not (c == 2 and n % 2 == 0))
    result = calibrate_rig(views, RIG_BOARD, cameras, ["a", "b", "c"], [None] * 3)
    assert (0, 2) not in result.shared
    assert rotation_angle_deg(result.rotations[2] @ rotations[2].T) < 0.05
    assert np.linalg.norm(result.translations[2] - translations[2]) < 0.003


def test_a_camera_that_shares_no_view_is_refused_with_what_to_capture():
    cameras, _, _, views = exact_views(seed=5, instants=20, seen=lambda c, n: c != 2 or n >= 10)
    views = [v for v in views if not (v.camera != 2 and v.instant >= 10)]
    with pytest.raises(RigError, match=r"camera c sees the board at the same instant as another camera in 0 view.*"
                                       r"hold the board where c and one of a, b both see it"):
        calibrate_rig(views, RIG_BOARD, cameras, ["a", "b", "c"], [None] * 3)


def test_unsynchronised_videos_are_refused():
    cameras, _, _, views = exact_views(seed=6, instants=24)
    late = [RigView(v.camera, (v.instant + 3) % 24 if v.camera == 1 else v.instant, v.ids, v.corners) for v in views]
    with pytest.raises(RigError, match="not synchronised.*--sync-offsets"):
        calibrate_rig(late, RIG_BOARD, cameras, ["a", "b", "c"], [None] * 3)


def test_a_misdetected_view_is_dropped_and_said():
    cameras, rotations, _, views = exact_views(seed=7, instants=24)
    target = next(v for v in views if v.camera == 1 and len(v.ids) > 20)
    target.corners = target.corners + np.random.default_rng(0).normal(0, 2.5, target.corners.shape)
    result = calibrate_rig(views, RIG_BOARD, cameras, ["a", "b", "c"], ["k1 k2"] * 3)
    assert any(d.camera == 1 and d.instant == target.instant for d in result.dropped)
    assert rotation_angle_deg(result.rotations[1] @ rotations[1].T) < 0.05


# ----------------------------------------------------------------------------------------- the command
@pytest.fixture(scope="module")
def drawn(tmp_path_factory):
    """Three cameras' folders of drawn frames (good light) and the truth."""
    truth = drawn_rig(RIG_BOARD, seed=11, instants=16)
    root = tmp_path_factory.mktemp("rig")
    folders = truth.save_frames(root)
    board = RIG_BOARD.save(root / "board.yaml")
    return truth, folders, board


def test_the_command_calibrates_a_rig_into_camera_files_a_toml_and_a_report(tmp_path, drawn, capsys, monkeypatch):
    import deepcharuco.cli.calibrate_rig as rig_command

    truth, folders, board = drawn
    solved, solve = [], rig_command.solve_rig

    def kept(*args, **kwargs):  # the command's RigResult, kept for --origin board's default instant below
        solved.append(solve(*args, **kwargs))
        return solved[-1]

    monkeypatch.setattr(rig_command, "solve_rig", kept)
    out = tmp_path / "rig"
    assert main([*map(str, folders), "--board", str(board), "--detector", "opencv", "--out", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "3 cameras" in printed and "shared instants: cam0-cam1" in printed
    toml = tomllib.loads((out / "rig.toml").read_text())
    for c in range(3):
        camera = read_camera(out / f"cam{c}.yaml")
        assert abs(camera.K[0, 0] / truth.cameras[c].K[0, 0] - 1) < 0.01
        storage = cv2.FileStorage(str(out / f"cam{c}.yaml"), cv2.FILE_STORAGE_READ)
        R, t = storage.getNode("rotation_matrix").mat(), storage.getNode("translation_vector").mat().ravel()
        assert storage.getNode("detector").string() == "opencv" and storage.getNode("network").empty()
        assert rotation_angle_deg(R @ truth.rotations[c].T) < 0.5
        assert np.linalg.norm(t - truth.translations[c]) < 0.01
        entry = toml[f"cam_{c}"]
        assert entry["name"] == f"cam{c}" and entry["size"] == list(SIZE)
        assert np.allclose(cv2.Rodrigues(np.array(entry["rotation"]))[0], R, atol=1e-9)
        assert np.allclose(entry["translation"], t) and np.allclose(entry["matrix"], camera.K)
    assert (out / "rig_report.html").read_bytes().startswith(b"<!doctype html><html><head><meta charset='utf-8'><title>Rig")
    assert "every corner weighed alike" in (out / "rig_report.html").read_text()  # OpenCV's corners carry no covariance
    # --origin board without --origin-instant (`board_origin` on the command's solve; run through the command just
    # below with an instant): the rig in the board's frame at an instant every camera saw it; the cameras keep their
    # relative poses.
    (instant, _), moved = board_origin(solved[0])
    assert sum(view.key == (instant, 0) for view in solved[0].views) == 3
    assert rotation_angle_deg(moved.rotations[1] @ moved.rotations[0].T @ truth.rotations[1].T) < 0.5
    assert np.linalg.norm(moved.translations[0] - truth.board_translations[instant]) < 0.01
    # --origin board at a chosen instant: the board's origin there is the rig's origin, seen by camera 0 where the
    # truth puts it.
    chosen = tmp_path / "instant"
    assert main([*map(str, folders), "--board", str(board), "--detector", "opencv", "--out", str(chosen), "--quiet",
                 "--origin", "board", "--origin-instant", "4", "--no-report"]) == 0
    toml_chosen = tomllib.loads((chosen / "rig.toml").read_text())
    assert toml_chosen["metadata"]["frame"] == "the board's at instant 4"
    t0 = np.array(toml_chosen["cam_0"]["translation"])  # camera 0 sees the rig's origin (the board's) at t0
    assert np.linalg.norm(t0 - truth.board_translations[4]) < 0.01


def test_different_lengths_are_refused_and_nothing_is_written(tmp_path, drawn, capsys):
    _, folders, board = drawn
    short = tmp_path / "short"
    short.mkdir()
    for image in sorted(folders[1].iterdir())[:10]:
        (short / image.name).write_bytes(image.read_bytes())
    videos = []
    for folder in (folders[0], short):  # lengths are known before reading for videos
        path = tmp_path / f"{folder.name}.avi"
        images = [cv2.imread(str(p)) for p in sorted(folder.iterdir())]
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, SIZE)
        for image in images:
            writer.write(image)
        writer.release()
        videos.append(str(path))
    out = tmp_path / "rig"
    assert main([*videos, "--board", str(board), "--detector", "opencv", "--out", str(out), "--quiet",
                 "--sync", "frames"]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "different lengths (cam0 16, short 10 frames)" in error[0] and "--sync-offsets" in error[0]
    assert not any(out.glob("*.yaml")) and not (out / "rig.toml").exists()


def test_a_camera_that_never_sees_the_board_is_refused(tmp_path, drawn, capsys):
    _, folders, board = drawn
    blank = tmp_path / "blank"
    blank.mkdir()
    for image in sorted(folders[1].iterdir()):
        cv2.imwrite(str(blank / image.name), np.full((SIZE[1], SIZE[0]), 90, np.uint8))
    out = tmp_path / "rig"
    assert main([str(folders[0]), str(blank), "--board", str(board), "--detector", "opencv", "--out", str(out),
                 "--quiet"]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "never found by blank in 16 instants" in error[0]
    assert not out.exists()  # the folder this run made, empty, is gone again


@pytest.mark.parametrize("extra, message", [
    (["--out", "rig.yaml"], "names a file, but 2 sources make a rig"),
    (["--camera", "a.yaml"], "--camera given 1 times for 2 sources"),
    (["--sync-offsets", "0"], "--sync-offsets has 1 values for 2 sources"),
    (["--model", "fisheye", "--fix-k3"], "--fix-k3 is for the pinhole and rational models"),
])
def test_rig_options_are_checked_before_any_work(tmp_path, drawn, capsys, extra, message, monkeypatch):
    _, folders, board = drawn
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) if extra[0] != "--out" else _no_raise():
        code = main([str(folders[0]), str(folders[1]), "--board", str(board), "--detector", "opencv", *extra])
        assert code == 2
    assert message in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_one_source_with_rig_options_is_refused(drawn, capsys):
    _, folders, board = drawn
    with pytest.raises(SystemExit) as stop:
        main([str(folders[0]), "--board", str(board), "--camera", "x.yaml"])
    assert stop.value.code == 2 and "--camera is for a rig (two sources or more)" in capsys.readouterr().err


class _no_raise:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def test_two_boards_link_cameras_that_never_see_the_same_one_as_the_first():
    # Camera 0 sees board A only, camera 2 board B only, camera 1 both: one rig through camera 1.
    other = BoardSpec(squares_x=9, squares_y=6, square_length=0.06, marker_length=0.045, dictionary="DICT_6X6_250",
                      first_marker_id=27)
    rng = np.random.default_rng(8)
    cameras, rotations, translations, target = rig_cameras(rng, 3, SIZE)
    poses = [board_poses(rng, board, target, 20) for board in (RIG_BOARD, other)]
    views = []
    for c, (camera, R, t) in enumerate(zip(cameras, rotations, translations)):
        for b, board in enumerate((RIG_BOARD, other)):
            if (c, b) in ((0, 1), (2, 0)):
                continue
            points = board.object_points()
            for n in range(20):
                R_c, t_c = R @ poses[b][0][n], R @ poses[b][1][n] + t
                pixels = camera.project(points, cv2.Rodrigues(R_c)[0], t_c)
                inside = ((pixels > 15) & (pixels < np.array(SIZE) - 15)).all(1)
                if inside.sum() >= 6:
                    views.append(RigView(c, n, np.flatnonzero(inside), pixels[inside] + rng.normal(0, 0.1, (inside.sum(), 2)),
                                         board=b))
    result = calibrate_rig(views, [RIG_BOARD, other], cameras, ["a", "b", "c"], [None] * 3)
    assert {b for _, b in result.board_poses} == {0, 1} and (0, 2) not in result.shared
    for c in (1, 2):
        assert rotation_angle_deg(result.rotations[c] @ rotations[c].T) < 0.05
        assert np.linalg.norm(result.translations[c] - translations[c]) < 0.003


def test_one_detector_finds_each_of_several_boards(tmp_path, capsys):
    from deepcharuco import Detector
    from deepcharuco.boards.synthetic import look_at_pose, render_board_view
    from deepcharuco.cli.detect import main as detect_main

    a = BoardSpec(squares_x=5, squares_y=4, square_length=0.04, marker_length=0.03, dictionary="DICT_4X4_50")
    b = BoardSpec(squares_x=5, squares_y=4, square_length=0.04, marker_length=0.03, dictionary="DICT_4X4_50",
                  first_marker_id=10)
    K = np.array([[500.0, 0, 319.5], [0, 500, 239.5], [0, 0, 1]])
    views = [look_at_pose(a, 0.6, 15, -10, 5, offset=(-0.12, 0)), look_at_pose(b, 0.6, -10, 15, -5, offset=(0.12, 0))]
    drawn = [render_board_view(board, K, *pose, (640, 480)) for board, pose in zip((a, b), views)]
    image = np.where(drawn[0] != 90, drawn[0], drawn[1]).astype(np.uint8)  # both boards on one grey background
    detector = Detector(boards=[a, b])
    for board, pose, detection in zip((a, b), views, detector.detect_boards(image)):
        truth = Camera(K, np.zeros(5), (640, 480)).project(board.object_points(), *pose)
        assert len(detection.ids) == board.num_corners
        assert np.linalg.norm(detection.corners - truth[detection.ids], axis=1).max() < 1.0
    with pytest.raises(Exception, match="detect_boards"):
        detector.detect(image)
    with pytest.raises(Exception, match=r"boards\[0\] and boards\[1\] both print markers 0-9 of DICT_4X4"):
        Detector(boards=[a, a])
    # Boards that share markers (a family's dictionaries share their first markers) are refused: searched together, the
    # second was found on the first's squares, with a pose (a phantom board).
    overlapping = BoardSpec(squares_x=4, squares_y=4, square_length=0.04, marker_length=0.03,
                            dictionary="DICT_4X4_1000", first_marker_id=5)
    with pytest.raises(Exception, match="both print markers 5-9 of DICT_4X4"):
        Detector(boards=[a, b, overlapping])
    assert b.shared_markers(overlapping) == (10, 12) and a.shared_markers(b) is None
    assert a.shared_markers(BoardSpec(5, 4, 0.04, 0.03, "DICT_5X5_50")) is None  # another family: other codes
    # The command: one CSV and JSON per board, named after the board files.
    cv2.imwrite(str(tmp_path / "two.png"), image)
    a.save(tmp_path / "left.yaml")
    b.save(tmp_path / "right.yaml")
    assert detect_main([str(tmp_path / "two.png"), "--board", str(tmp_path / "left.yaml"), "--board",
                        str(tmp_path / "right.yaml"), "--detector", "deep", "--out", str(tmp_path / "out")]) == 0
    import json

    for name in ("left", "right"):
        frames = json.loads((tmp_path / "out" / f"two_{name}.json").read_text())["frames"]
        assert frames[0]["num_corners"] == 12
    assert (tmp_path / "out" / "two_left.csv").is_file() and (tmp_path / "out" / "two_overlay.png").is_file()
    overlapping.save(tmp_path / "third.yaml")
    capsys.readouterr()
    assert detect_main([str(tmp_path / "two.png"), "--board", str(tmp_path / "left.yaml"), "--board",
                        str(tmp_path / "third.yaml"), "--out", str(tmp_path / "out3")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "left.yaml and " in err[0] and "third.yaml both print markers 5-9" in err[0]
    assert not (tmp_path / "out3").exists()


@needs_bpy
def test_rendered_rig_has_the_drawn_rigs_truth_and_resumes(tmp_path):
    import json

    from evaluate.calibration.rig_renders import run as render_rig

    size = (160, 120)
    assert render_rig(RIG_BOARD, tmp_path, seed=3, cameras=2, instants=6, size=size, conditions=["good"],
                      threads=1, quiet=True) == 12
    truth = json.loads((tmp_path / "truth.json").read_text())
    drawn = drawn_rig(RIG_BOARD, seed=3, cameras=2, instants=6, size=size)  # the same rig and waving
    for c in range(2):
        assert np.allclose(truth["cameras"][c]["K"], drawn.cameras[c].K)
        assert np.allclose(truth["cameras"][c]["R"], drawn.rotations[c])
        images = sorted((tmp_path / "good" / f"cam{c}").glob("*.png"))
        assert len(images) == 6 and cv2.imread(str(images[0]), cv2.IMREAD_GRAYSCALE).shape == (120, 160)
    assert render_rig(RIG_BOARD, tmp_path, seed=3, cameras=2, instants=6, size=size, conditions=["good"],
                      threads=1, quiet=True) == 0  # resumed: nothing left to render


def test_sync_offsets_line_up_sources_that_started_apart(tmp_path, drawn, capsys):
    truth, folders, board = drawn
    late = tmp_path / "late1"  # camera 1 started 3 frames after the others: its first frame shows instant 3
    late.mkdir()
    for image in sorted(folders[1].iterdir())[3:]:
        (late / image.name).write_bytes(image.read_bytes())
    sources = [str(folders[0]), str(late), str(folders[2])]
    out = tmp_path / "rig"
    assert main([*sources, "--board", str(board), "--detector", "opencv", "--out", str(out), "--quiet",
                 "--sync", "frames"]) == 2
    assert "different lengths (cam0 16, late1 13, cam2 16 frames)" in capsys.readouterr().err
    assert main([*sources, "--board", str(board), "--detector", "opencv", "--out", str(out), "--quiet",
                 "--no-report", "--sync-offsets", "3", "0", "3"]) == 0
    storage = cv2.FileStorage(str(out / "late1.yaml"), cv2.FILE_STORAGE_READ)
    assert rotation_angle_deg(storage.getNode("rotation_matrix").mat() @ truth.rotations[1].T) < 0.5


def test_timestamps_pair_frames_of_cameras_with_their_own_clocks(tmp_path, drawn):
    truth, folders, board = drawn
    # Camera 1 started 3 frames late and its clock runs 5 ms off; camera 2 dropped frame 5.
    rows = ["source,frame,time_s"]
    rows += [f"cam0,{n},{n / 6:.4f}" for n in range(16)]
    rows += [f"cam1,{n - 3},{n / 6 + 0.005:.4f}" for n in range(3, 16)]
    rows += [f"2,{k},{n / 6:.4f}" for k, n in enumerate(n for n in range(16) if n != 5)]
    (tmp_path / "times.csv").write_text("\n".join(rows) + "\n")
    late, dropped = tmp_path / "cam1", tmp_path / "cam2"
    late.mkdir()
    dropped.mkdir()
    for image in sorted(folders[1].iterdir())[3:]:
        (late / image.name).write_bytes(image.read_bytes())
    for image in sorted(folders[2].iterdir()):
        if image.name != "005.png":
            (dropped / image.name).write_bytes(image.read_bytes())
    from deepcharuco.cli.calibrate_rig import instants_by_time, read_timestamps

    mapping = instants_by_time(read_timestamps(tmp_path / "times.csv", ["cam0", "cam1", "cam2"]))
    assert mapping[1][0] == 3 and mapping[2][5] == 6 and len(mapping[2]) == 15
    out = tmp_path / "rig"
    assert main([str(folders[0]), str(late), str(dropped), "--board", str(board), "--detector", "opencv", "--out",
                 str(out), "--quiet", "--no-report", "--timestamps", str(tmp_path / "times.csv")]) == 0
    for c, name in ((1, "cam1"), (2, "cam2")):
        storage = cv2.FileStorage(str(out / f"{name}.yaml"), cv2.FILE_STORAGE_READ)
        assert rotation_angle_deg(storage.getNode("rotation_matrix").mat() @ truth.rotations[c].T) < 0.5


def test_jobs_detect_a_rig_on_worker_processes_and_write_the_same_files(tmp_path, drawn):
    """``--jobs 2``: the three cameras' frames detected on two worker processes (`deepcharuco.detection.parallel`) give the
    camera files and the rig file one process gives (to rounding: `assert_same_but_rounding`)."""
    truth, folders, board = drawn
    written = []
    for jobs in (1, 2):
        out = tmp_path / f"jobs{jobs}"
        assert main([*map(str, folders), "--board", str(board), "--detector", "deep", "--out", str(out), "--quiet",
                     "--no-report", "--jobs", str(jobs)]) == 0
        written.append({path.name: path.read_text() for path in sorted(out.iterdir())})
    assert sorted(written[0]) == sorted(written[1]) and len(written[0]) == 4
    for name in written[0]:
        assert_same_but_rounding(written[0][name], written[1][name])


def test_a_frame_a_reader_skipped_shifts_no_other_frame_of_its_camera(tmp_path, drawn, capsys):
    """Camera 1 as a video whose frame 7 is noise (the decoder rejects it; `VideoFrames` skips it and keeps the
    frame numbers), camera 2 as a folder whose 009.png is not an image: their other frames still pair with camera
    0's of the same instant, so each camera is placed where the truth has it. (Paired by their place in the streams,
    every frame after the damage met the next instant's: cameras placed centimetres off, exit 0.)"""
    truth, folders, board = drawn
    video = tmp_path / "cam1.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, SIZE)
    for image in sorted(folders[1].iterdir()):
        writer.write(cv2.imread(str(image)))
    writer.release()
    data = bytearray(video.read_bytes())
    starts = [i for i in range(len(data) - 1) if data[i:i + 2] == b"\xff\xd8"]  # each frame is one JPEG (MJPG)
    a, b = starts[7], starts[8] - 8  # frame 7's JPEG, up to the next frame's chunk header
    data[a:b] = np.random.default_rng(52).integers(0, 256, b - a, dtype=np.uint8).tobytes()
    video.write_bytes(bytes(data))
    folder = tmp_path / "cam2"
    folder.mkdir()
    for image in sorted(folders[2].iterdir()):
        (folder / image.name).write_bytes(b"not an image" if image.name == "009.png" else image.read_bytes())
    out = tmp_path / "rig"
    assert main([str(folders[0]), str(video), str(folder), "--board", str(board), "--detector", "opencv", "--out",
                 str(out), "--quiet", "--no-report"]) == 0
    err = capsys.readouterr().err
    assert "cam1: 1 frame(s) could not be decoded" in err and "cam2: 1 image(s) skipped, each named above" in err
    for c in (1, 2):
        storage = cv2.FileStorage(str(out / f"cam{c}.yaml"), cv2.FILE_STORAGE_READ)
        R, t = storage.getNode("rotation_matrix").mat(), storage.getNode("translation_vector").mat().ravel()
        assert rotation_angle_deg(R @ truth.rotations[c].T) < 0.5
        assert np.linalg.norm(t - truth.translations[c]) < 0.01
        assert (7 if c == 1 else 9) not in storage.getNode("view_frames").mat().ravel()


def test_one_board_or_one_recording_given_twice_is_refused(tmp_path, drawn, capsys):
    """The same --board twice (or a copy of it) would count every view twice (97 views became 194, the deviations
    shrank by 1/sqrt 2); the same folder under a second name (a link) or a copy of it would be two cameras in one
    place. Each: one line, exit 2, nothing written."""
    _, folders, board = drawn
    copy = tmp_path / "copy.yaml"
    copy.write_bytes(board.read_bytes())
    link = tmp_path / "again"
    link.symlink_to(folders[1], target_is_directory=True)
    twin = tmp_path / "twin"
    twin.mkdir()
    for image in folders[1].iterdir():
        (twin / image.name).write_bytes(image.read_bytes())
    smaller = tmp_path / "smaller.yaml"  # the same dictionary's first markers on a board of one row fewer
    spec = BoardSpec.load(board)
    BoardSpec(spec.squares_x, spec.squares_y - 1, spec.square_length, spec.marker_length, spec.dictionary).save(smaller)
    out = tmp_path / "rig"
    cases = [([str(folders[0]), str(folders[1]), "--board", str(board), "--board", str(copy)], "are one board"),
             ([str(folders[0]), str(folders[1]), "--board", str(board), "--board", str(smaller)], "both print markers"),
             ([str(folders[0]), str(folders[1]), str(link), "--board", str(board)], "are one recording"),
             ([str(folders[0]), str(folders[1]), str(twin), "--board", str(board)], "are one recording")]
    for sources, message in cases:
        assert main([*sources, "--detector", "opencv", "--out", str(out), "--quiet"]) == 2
        error = capsys.readouterr().err.strip().splitlines()
        assert len(error) == 1 and message in error[0], error
        assert not out.exists()


def test_a_camera_file_the_rig_cannot_hold_as_it_is_is_refused(tmp_path, drawn, capsys):
    """A held --camera file with a skew, or with thin-prism / tilt terms (12 or 14 coefficients), was held and written
    without them (the rig models fx fy cx cy and 8 terms), exit 0; now one line, exit 2, before any frame is read.
    Terms past the eighth that are all 0 hold nothing and are taken."""
    _, folders, board = drawn
    K = np.array([[520.0, 0.0, 322.3], [0.0, 518.0, 236.8], [0.0, 0.0, 1.0]])
    skewed = K.copy()
    skewed[0, 1] = 0.8
    files = {"skew": (skewed, np.zeros(5)), "prism": (K, np.r_[np.zeros(8), 1e-3, 0, 0, 0]),
             "zeros": (K, np.zeros(14))}
    for name, (matrix, dist) in files.items():
        write_camera(tmp_path / f"{name}.yaml", Camera(matrix, dist, (320, 240)))
    out = tmp_path / "rig"
    for name, message in (("skew", "holds a skew (camera_matrix[0][1] = 0.8)"),
                          ("prism", "distortion terms past the eighth (12 coefficients")):
        assert main([str(folders[0]), str(folders[1]), "--board", str(board), "--camera",
                     str(tmp_path / f"{name}.yaml"), "--camera", "-", "--detector", "opencv", "--out", str(out),
                     "--quiet"]) == 2
        error = capsys.readouterr().err.strip().splitlines()
        assert len(error) == 1 and message in error[0] and "or - to solve that camera here" in error[0], error
        assert not out.exists()
    from deepcharuco.cli.calibrate_rig import held_as_given
    assert held_as_given(str(tmp_path / "zeros.yaml")).dist.size == 14


def test_folders_of_stills_of_different_lengths_say_so_when_no_motion_lines_them_up(tmp_path, drawn, capsys):
    """One image missing from one camera's folder of stills: the motion alignment tried for sources of other lengths
    fails, and the error said only that the board was seen in too few consecutive frames; it leads with the counts."""
    _, folders, board = drawn
    short = tmp_path / "short"
    short.mkdir()
    for image in sorted(folders[1].iterdir())[:-1]:
        (short / image.name).write_bytes(image.read_bytes())
    out = tmp_path / "rig"
    assert main([str(folders[0]), str(short), "--board", str(board), "--detector", "opencv", "--out", str(out),
                 "--quiet"]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "the folders hold different numbers of images (" in error[0], error
    assert "remove the images of an instant one camera lacks" in error[0] and not out.exists()


def test_a_binary_timestamps_file_is_one_line(tmp_path, drawn, capsys):
    """--timestamps given a binary file (a video by mistake) ended in UnicodeDecodeError's traceback."""
    _, folders, board = drawn
    binary = tmp_path / "times.csv"
    binary.write_bytes(np.random.default_rng(1).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    out = tmp_path / "rig"
    assert main([str(folders[0]), str(folders[1]), "--board", str(board), "--detector", "opencv", "--out", str(out),
                 "--quiet", "--timestamps", str(binary)]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "is not a text CSV" in error[0] and "source,frame,time_s" in error[0]
    assert not out.exists()


def _times(rows: list[str]) -> str:
    return "source,frame,time_s\n" + "\n".join(rows) + "\n"


GOOD_TIMES = [f"{c},{n},{n / 6:.4f}" for c in (0, 1) for n in range(16)]


@pytest.mark.parametrize("case, message", [
    ("offset past the end", "--sync-offsets 1000 for cam1 skips every one of its 16 frames"),
    ("empty video", "no frames could be read from empty:"),
    ("nan time", "line 2: time_s nan is not a time"),
    ("frame past the end", "frame 99 of cam1, whose frames are numbered 0..15"),
    ("negative frame", "frame -1 of cam0, whose frames are numbered 0..15"),
    ("all equal times", "cam0's times do not increase with its frame numbers"),
    ("conflicting rows", "frame 3 of cam1 again, at 9 s (before: 0.5 s)"),
    ("clocks never overlap", "no frame of cam1 was taken within half a frame interval of one of cam0's"),
    ("origin instant past the end", "--origin-instant 40: no camera found the board at that instant (of 16 read)"),
])
def test_rig_nonsense_is_refused_naming_the_source_before_the_solve(tmp_path, drawn, capsys, monkeypatch, case,
                                                                     message):
    """Wrong advice and accepted nonsense: --sync-offsets past a source's end blamed the other source, as did a 0-frame
    video; --timestamps with NaN times, frames past the end or negative, all-equal times, conflicting rows or clocks
    that never overlap ran on to "no frames could be read" or "board never found" (or the last row won); an
    --origin-instant past the recording was refused only after the whole solve. Each: one line naming the source or
    the line, exit 2, nothing written, and no solve started."""
    _, folders, board = drawn
    sources, extra = [str(folders[0]), str(folders[1])], []
    rows = list(GOOD_TIMES)
    if case == "offset past the end":
        extra = ["--sync-offsets", "0", "1000"]
    elif case == "empty video":
        empty = tmp_path / "empty.avi"
        cv2.VideoWriter(str(empty), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, SIZE).release()  # no frame written
        sources = [str(folders[0]), str(empty)]
    elif case == "origin instant past the end":
        extra = ["--origin", "board", "--origin-instant", "40"]
    else:
        rows = {"nan time": ["0,0,nan", *rows[1:]], "frame past the end": [*rows, "1,99,20.0"],
                "negative frame": ["0,-1,-0.1", *rows], "all equal times": [f"0,{n},1.0" for n in range(16)] + rows[16:],
                "conflicting rows": [*rows, "1,3,9"],
                "clocks never overlap": rows[:16] + [f"1,{n},{100 + n / 6:.4f}" for n in range(16)]}[case]
        (tmp_path / "times.csv").write_text(_times(rows))
        extra = ["--timestamps", str(tmp_path / "times.csv")]

    def no_solve(*args, **kwargs):
        raise AssertionError("solved before the refusal")

    monkeypatch.setattr("deepcharuco.cli.calibrate_rig.solve_rig", no_solve)
    out = tmp_path / "rig"
    assert main([*sources, "--board", str(board), "--detector", "opencv", "--out", str(out), "--quiet", *extra]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and message in error[0], error
    assert not out.exists() or not any(out.iterdir())


def test_the_bundle_adjustments_jacobian_in_closed_form_is_its_residuals_derivative(monkeypatch):
    # The closed form equals central differences to ~1e-9 relative (measured 4e-9; 1e-6 asserted): the rotations', the
    # projection's by every one of the 12 intrinsics (the rational model's k4-k6 too) and by the point, and the whole
    # residuals' with p1 p2 free, corner weights and intrinsics' priors.
    from scipy.optimize._numdiff import approx_derivative

    import deepcharuco.calibration.bundle as bundle
    from deepcharuco.calibration.rig_jacobian import pinhole_derivatives, residual_jacobian, rotation_derivatives

    rng = np.random.default_rng(0)
    points = np.c_[rng.uniform(-0.4, 0.4, (20, 2)), rng.uniform(0.8, 1.5, 20)]
    intrinsics = np.tile([600.0, 590.0, 320.0, 240.0, -0.2, 0.05, 0.001, -0.002, 0.01, 0.1, -0.02, 0.005], (20, 1))
    d_point, d_intrinsics = pinhole_derivatives(points, intrinsics)
    for k in range(12):
        step = np.zeros(12)
        step[k] = 1e-6 * max(1.0, abs(intrinsics[0, k]))
        central = (project(points, intrinsics + step) - project(points, intrinsics - step)) / (2 * step[k])
        assert np.abs(central - d_intrinsics[:, :, k]).max() < 1e-6 * max(1.0, np.abs(central).max()), k
    for k in range(3):
        step = np.eye(3)[k] * 1e-7
        central = (project(points + step, intrinsics) - project(points - step, intrinsics)) / 2e-7
        assert np.abs(central - d_point[:, :, k]).max() < 1e-6 * np.abs(central).max(), k

    for v in ([0.3, -1.2, 2.0], [1e-10, 0.0, 0.0], [0.0, 0.0, 0.0]):
        for i in range(3):
            step = np.eye(3)[i] * 1e-6
            central = (rotations_from_vectors(np.add(v, step))[0] - rotations_from_vectors(np.subtract(v, step))[0]) / 2e-6
            assert np.abs(central - rotation_derivatives(np.array([v]))[0, i]).max() < 1e-8
    captured = []
    solve = bundle.least_squares
    monkeypatch.setattr(bundle, "least_squares", lambda fun, x0, **kw: captured.append((fun.__self__, x0)) or solve(fun, x0, **kw))
    cameras, _, _, views = exact_views(seed=3, instants=6)
    rng = np.random.default_rng(1)
    views = [RigView(v.camera, v.instant, v.ids, v.corners,
                     covariances=np.einsum("nij,nkj->nik", m := rng.normal(0, 0.15, (len(v.ids), 2, 2)), m) + 0.01 * np.eye(2))
             for v in views]
    calibrate_rig(views, RIG_BOARD, perturbed(cameras), ["a", "b", "c"], ["k1 k2 p1 p2 k3"] * 3,
                  priors=[{"fx": 2.0, "cx": 3.0}, None, {"k1": 0.01}])
    problem, x0 = captured[-1]
    assert problem.roots is not None and np.isfinite(problem.prior_sigma).sum() == 3 and problem.free.sum() == 27
    exact = residual_jacobian(problem, x0).toarray()
    central = approx_derivative(problem.residuals, x0, method="3-point")
    assert np.abs(exact - central).max(axis=0).max() < 1e-6 * np.abs(central).max()
    assert np.all(np.abs(exact - central).max(axis=0) <= 1e-6 * (np.abs(central).max(axis=0) + 1e-9))
