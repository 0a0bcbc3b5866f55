"""deepcharuco.cli.calibrate on exact synthetic videos through a known distorted camera (datagen.lens)."""


import cv2
import numpy as np
import pytest

from conftest import ROOT, assert_same_but_rounding, make_view
from datagen.lens import distort_image, distortion_maps, pixels_to_rays, wide_camera
from deepcharuco import BoardSpec, Camera, OpenCVDetector, read_camera, write_camera
from deepcharuco.boards.synthetic import render_board_view
from deepcharuco.calibration.intrinsics import calibrate
from deepcharuco.calibration.views import CalibrationError, FrameDetection, SelectionOptions, sharpness, usable_reason
from deepcharuco.cli.calibrate import detect_frames, main
from deepcharuco.cli.common import jobs_warning
from evaluate.calibration.calibration_sequences import WavingPath, frame_times, hand_waved_pose, pose_of, true_camera

BOARD = BoardSpec()
SIZE = (320, 240)
FRAMES = 60


@pytest.fixture(scope="module")
def waved():
    """(images, K, dist): a board waved over the image of a barrel-distorted camera (k1 = -0.3)."""
    rng = np.random.default_rng(7)
    K, dist = true_camera(rng, -0.3, SIZE)
    K_wide, wide_size = wide_camera(K, dist, SIZE, scale=2.0)
    maps = distortion_maps(K, dist, SIZE, K_wide)
    path = WavingPath.draw(rng)
    images = []
    for t in frame_times(FRAMES, rng):
        rvec, tvec = pose_of(hand_waved_pose(path, t, BOARD, K, dist, SIZE))
        wide = render_board_view(BOARD, K_wide, rvec, tvec, wide_size, supersample=2)
        images.append(distort_image(wide, K, dist, SIZE, K_wide, maps=maps))
    return images, K, dist


@pytest.fixture(scope="module")
def detections(waved):
    frames, size = detect_frames(((i, str(i), image) for i, image in enumerate(waved[0])), OpenCVDetector(BOARD), quiet=True)
    assert size == SIZE
    return frames


@pytest.fixture(scope="module")
def calibrated(detections):
    """(result, bootstrap): the default calibration of the waved frames (every step), and its call of
    `bootstrap_std` ((args, kwargs), the spread it returned) as calibrate made it."""
    import deepcharuco.calibration.intrinsics as intrinsics

    calls, bootstrap_std = [], intrinsics.bootstrap_std

    def recorded(*args, **kwargs):
        calls.append(((args, kwargs), bootstrap_std(*args, **kwargs)))
        return calls[-1][1]

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(intrinsics, "bootstrap_std", recorded)
        result = calibrate(detections, BOARD, SIZE)
    assert len(calls) == 1
    return result, calls[0]


def _video(path, images):
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, SIZE)
    for image in images:
        writer.write(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))
    writer.release()
    return path


def test_calibration_recovers_the_true_camera(waved, calibrated):
    _, K, dist = waved
    result, _ = calibrated
    estimate = result.camera.K
    # Within 3 of its own standard deviations (they are honest) and within 0.6 % / 2.5 px outright.
    for (row, col), name in (((0, 0), "fx"), ((1, 1), "fy"), ((0, 2), "cx"), ((1, 2), "cy")):
        assert abs(estimate[row, col] - K[row, col]) < 3 * result.std[name] + 0.05, name
    assert abs(estimate[0, 0] / K[0, 0] - 1) < 0.006 and abs(estimate[1, 1] / K[1, 1] - 1) < 0.006
    assert np.abs(estimate[:2, 2] - K[:2, 2]).max() < 2.5
    assert abs(result.camera.dist[0] - dist[0]) < 0.03
    assert result.rms < 0.3 and len(result.views) >= 40
    # Every frame is accounted for, once.
    assert sorted(d.index for d in result.decisions) == list(range(FRAMES))
    assert sum(d.status == "kept" for d in result.decisions) == len(result.views)


def test_cli_with_jobs_writes_the_same_camera_file(tmp_path, waved, capsys, monkeypatch):
    """Frames detected on 2 worker processes (`deepcharuco.detection.parallel`) calibrate the camera one process does (to
    rounding: `assert_same_but_rounding`); 2 workers on 2 CPUs are warned of (they share them with the reading)."""
    images, _, _ = waved
    video = _video(tmp_path / "wave.avi", images[:12])
    monkeypatch.setattr("deepcharuco.cli.common.available_cpus", lambda: 2)
    texts = []
    for jobs in (1, 2):
        out = tmp_path / f"jobs{jobs}.yaml"
        assert main([str(video), "--out", str(out), "--quiet", "--no-report", "--min-views", "4",
                     "--jobs", str(jobs)]) == 0
        texts.append(out.read_text())
        warned = "warning: --jobs 2 on 2 CPU(s)" in capsys.readouterr().err
        assert warned == (jobs == 2)
    assert_same_but_rounding(*texts)


def test_jobs_at_or_above_the_cpus_are_warned_of():
    assert jobs_warning(1, cpus=1) is None and jobs_warning(2, cpus=4) is None and jobs_warning(3, cpus=4) is None
    assert "--jobs 4 on 4 CPU(s)" in jobs_warning(4, cpus=4)
    assert "--jobs 8 on 2 CPU(s)" in jobs_warning(8, cpus=2)


def test_cli_writes_a_camera_file_opencv_reads_and_a_report(tmp_path, waved):
    images, K, dist = waved
    video = _video(tmp_path / "wave.avi", images)
    out = tmp_path / "cams" / "camera.yaml"
    assert main([str(video), "--out", str(out), "--quiet"]) == 0
    camera = read_camera(out)
    assert camera.image_size == SIZE and camera.dist.shape == (5,)
    # The default calibrate on these drawn frames (2026-11-27, the lite networks): fx and fy within 7e-5 of the truth,
    # the principal point within 0.05 and 0.10 px, k1 within 5e-4, RMS 0.018 px. With --network auto, the default
    # since 2026-12-07: fx and fy within 1.2e-4 and 2.0e-4, their own deviations 1.6e-4 (0.04 px), the principal
    # point within 0.004 and 0.10 px, k1 within 1e-4. Asserted within ~2 deviations, ~3x of the best.
    assert abs(camera.K[0, 0] / K[0, 0] - 1) < 3e-4 and abs(camera.K[1, 1] / K[1, 1] - 1) < 3e-4
    assert np.abs(camera.K[:2, 2] - K[:2, 2]).max() < 0.3 and abs(camera.dist[0] - dist[0]) < 0.0015
    storage = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    assert storage.getNode("distortion_model").string() == "pinhole"
    assert storage.getNode("detector").string() == "deep" and storage.getNode("network").string() == "auto"
    # One deviation per parameter solved: fx fy cx cy and the distortion terms chosen (p1 p2 may be held at 0).
    terms = storage.getNode("distortion_terms").string().split()
    assert terms[:2] == ["k1", "k2"] and storage.getNode("std_intrinsics").mat().shape == (4 + len(terms), 1)
    assert storage.getNode("std_intrinsics_names").string().split() == ["fx", "fy", "cx", "cy", *terms]
    held_out = storage.getNode("held_out_rms_px").mat()
    assert held_out.shape == (2, 1) and held_out.max() < 0.04  # 0.017 px
    assert storage.getNode("avg_reprojection_error").real() < 0.04
    storage.release()
    report = (tmp_path / "cams" / "camera_report.html").read_text()
    for text in ("RMS reprojection error", "Coverage", "alt=\"distortion\"", "Views kept and dropped", "std dev",
                 "Views weighed by their residuals"):
        assert text in report
    assert report.count("data:image/png;base64,") == 4


def test_fisheye_model_writes_four_coefficients(tmp_path, detections):
    result = calibrate(detections, BOARD, SIZE, "fisheye")
    assert result.camera.dist.shape == (4,) and result.std == {} and result.rms < 0.5
    assert result.camera.model == "fisheye"


def test_fisheye_file_reads_back_as_fisheye(tmp_path, waved):
    images, K, dist = waved
    out = tmp_path / "fisheye.yaml"
    assert main([str(_video(tmp_path / "wave.avi", images)), "--out", str(out), "--model", "fisheye", "--quiet",
                 "--no-report"]) == 0
    camera = read_camera(out)
    # Read as a pinhole camera, its k1..k4 would be k1 k2 p1 p2: the file must say which model it is.
    assert camera.model == "fisheye" and camera.dist.shape == (4,)
    storage = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    assert storage.getNode("distortion_model").string() == "fisheye"
    storage.release()
    # The model read back maps the true camera's rays where the true camera does (an equidistant fit of a
    # k1 = -0.3 lens: within a pixel over the middle of the image, where the board was).
    truth = Camera(K=K, dist=dist, image_size=SIZE)
    xs, ys = np.meshgrid(np.linspace(60, 260, 9), np.linspace(50, 190, 7))
    pixels = np.stack([xs.ravel(), ys.ravel()], 1)
    rays = pixels_to_rays(pixels, K, dist)  # Newton to 1e-12 (cv2.undistortPoints stops 1e-3 px short)
    points = np.column_stack([rays, np.ones(len(rays))])
    mapped = camera.project(points, np.zeros(3), np.zeros(3))
    assert np.abs(mapped - pixels).max() < 1.0
    # undistort_points inverts each model: back onto the rays, in an undistorted image with the same K.
    np.testing.assert_allclose(truth.undistort_points(pixels), rays * K[[0, 1], [0, 1]] + K[:2, 2], atol=1e-4)
    np.testing.assert_allclose(camera.undistort_points(mapped), rays * camera.K[[0, 1], [0, 1]] + camera.K[:2, 2],
                               atol=1e-4)
    # write_camera and read_camera keep the model; a pinhole file names none (OpenCV's samples' format).
    write_camera(tmp_path / "again.yaml", camera)
    again = read_camera(tmp_path / "again.yaml")
    assert again.model == "fisheye" and np.array_equal(again.dist, camera.dist)
    write_camera(tmp_path / "pinhole.yaml", truth)
    assert "distortion_model" not in (tmp_path / "pinhole.yaml").read_text()
    assert read_camera(tmp_path / "pinhole.yaml").model == "pinhole"


def test_a_wrong_corner_costs_itself_and_a_wrong_view_is_dropped(detections, without_bootstrap):
    frames = [FrameDetection(f.index, f.name, f.ids, f.corners.copy(), f.sharpness) for f in detections]
    full = [f for f in frames if len(f.ids) >= 12]
    full[0].corners[3] += (12.0, -9.0)  # one wrong corner
    full[1].corners += np.random.default_rng(0).normal(0.0, 4.0, full[1].corners.shape)  # a view of garbage
    result = calibrate(frames, BOARD, SIZE)
    decisions = {d.index: d for d in result.decisions}
    assert decisions[full[0].index].status == "kept", decisions[full[0].index]
    assert "1 outlier corner(s) dropped" in decisions[full[0].index].reason
    assert decisions[full[1].index].status == "dropped" and decisions[full[1].index].stage == "outlier"
    assert result.rms < 0.3


def test_near_duplicates_and_blurred_views_are_dropped(detections, without_bootstrap):
    frames = list(detections)
    twin = frames[10]
    frames.append(FrameDetection(FRAMES, "twin", twin.ids, twin.corners + 0.3, twin.sharpness * 0.9))
    frames.append(FrameDetection(FRAMES + 1, "blurred", frames[20].ids, frames[20].corners + 25.0, 1e-4))
    result = calibrate(frames, BOARD, SIZE)
    decisions = {d.name: d for d in result.decisions}
    assert decisions["twin"].reason == f"near-duplicate of frame {twin.name}"
    assert decisions["blurred"].reason.startswith("blurred")


def test_max_views_keeps_the_most_varied(detections, without_bootstrap):
    result = calibrate(detections, BOARD, SIZE, options=SelectionOptions(max_views=12))
    assert len(result.views) <= 12
    centres = np.array([v.corners.mean(0) for v in result.views])
    # Farthest-point selection: the kept views spread over the image, not one region of it.
    assert np.ptp(centres[:, 0]) > 0.4 * SIZE[0] and np.ptp(centres[:, 1]) > 0.3 * SIZE[1]
    assert sum("not needed" in d.reason for d in result.decisions) > 0


def test_sharpness_falls_with_blur_not_with_light(detections, waved):
    image = waved[0][5]
    corners = detections[5].corners
    blurred = cv2.blur(image, (9, 1))
    darker = (image * 0.3).astype(np.uint8)
    assert sharpness(blurred, corners) < 0.6 * sharpness(image, corners)
    assert sharpness(darker, corners) == pytest.approx(sharpness(image, corners), rel=0.2)


def test_one_line_of_corners_is_not_a_view():
    frame = FrameDetection(0, "row", np.arange(4), np.stack([np.arange(4) * 30.0 + 50, np.full(4, 100.0)], 1))
    assert usable_reason(frame, BOARD, 4) == "corners along one line of the board"


def _fail(tmp_path, capsys, images):
    video = _video(tmp_path / "bad.avi", images)
    out = tmp_path / "camera.yaml"
    code = main([str(video), "--out", str(out), "--quiet"])
    message = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and not out.exists() and not (tmp_path / "camera_report.html").exists()
    assert len(message) == 1 and message[0].startswith("error: ")
    return message[0]


def test_no_board_says_so(tmp_path, capsys):
    message = _fail(tmp_path, capsys, [np.full((240, 320), 90 + i, np.uint8) for i in range(8)])
    assert "no board found in any of 8 frames" in message and "--board" in message
    # --out in folders that do not exist yet: the failed run leaves none of them behind; a folder it did not make stays
    video = _video(tmp_path / "blank.avi", [np.full((240, 320), 90, np.uint8)] * 4)
    assert main([str(video), "--out", str(tmp_path / "new" / "deeper" / "camera.yaml"), "--quiet"]) == 2
    assert not (tmp_path / "new").exists()
    (tmp_path / "kept").mkdir()
    assert main([str(video), "--out", str(tmp_path / "kept" / "camera.yaml"), "--quiet"]) == 2
    assert (tmp_path / "kept").is_dir()


def test_too_few_views_says_what_to_capture(tmp_path, capsys, waved):
    message = _fail(tmp_path, capsys, waved[0][:3] + [np.full((240, 320), 90, np.uint8)] * 3)
    assert "only 3 usable view(s)" in message and "6 are needed" in message and "capture the board" in message


def test_one_tilt_everywhere_is_refused(tmp_path, capsys):
    camera = Camera.from_fov(*SIZE, hfov_deg=60.0)
    # The board fronto-parallel at eight places: the homographies differ, the focal length is not observable.
    images = [make_view(BOARD, camera, distance=0.4, offset=(dx, dy))[0]
              for dx in (-0.08, 0.0, 0.08) for dy in (-0.05, 0.05, 0.0)][:8]
    message = _fail(tmp_path, capsys, images)
    assert "one tilt" in message and "tilted" in message


def test_mixed_frame_sizes_are_refused():
    frames = [(0, "a", np.zeros((240, 320), np.uint8)), (1, "b", np.zeros((480, 640), np.uint8))]
    with pytest.raises(CalibrationError, match="one camera at one resolution"):
        detect_frames(iter(frames), OpenCVDetector(BOARD), quiet=True)


def test_an_output_that_is_a_folder_is_refused_before_any_work(tmp_path, capsys):
    code = main(["missing.avi", "--out", str(tmp_path), "--quiet"])
    assert code == 2 and "is a folder" in capsys.readouterr().err


def test_the_report_section_measures_each_detector_against_the_truth(tmp_path, waved, without_bootstrap):
    from datagen.shards import FrameLabels, write_shard
    from evaluate.calibration.calibration_eval import calibration_experiment, calibration_sections

    images, K, dist = waved
    meta = {"has_board": True, "sequence": "k1-0.3-good",
            **{f"dist_{n}": float(v) for n, v in zip(("k1", "k2", "p1", "p2", "k3"), dist)}}
    frames = [FrameLabels(image=image, corners=np.full((16, 2), np.nan, np.float32), visible=np.zeros(16, bool),
                          K=K.astype(np.float32), rvec=np.zeros(3), tvec=np.zeros(3), meta=meta) for image in images]
    write_shard(tmp_path, 0, frames, BOARD, {"command": "test"})
    results = calibration_experiment({"opencv": OpenCVDetector(BOARD)}, tmp_path, BOARD, quiet=True)
    cell = results["table"][0]["opencv"]
    assert cell["calibrated"] and cell["views"] >= 40 and cell["frames_with_corners"] == FRAMES
    assert abs(cell["fx_pct"]) < 0.6 and abs(cell["cx_px"]) < 2.5
    # The image's corners lie beyond the views' corners (the board never reaches them): the solved distortion is
    # extrapolated there, yet must hold most of the true one.
    assert cell["true_corner_distortion_px"] > 20
    assert max(cell["corner_distortion_error_px"], cell["mapping_error_px"]) < 0.15 * cell["true_corner_distortion_px"]
    assert [t["sequence"] for t in results["targets"]] == ["k1-0.3-good"]
    (title, text, rows, _), = calibration_sections(results)
    assert "Targets met" in text and rows[1][:2] == ["k1-0.3-good", "opencv"]
    from evaluate.documents import sections

    titles = [section[0] for section in sections({"calibration": results})]
    assert "Camera calibration on rendered sequences" in titles  # the evaluation report shows it


def test_fix_k3_keeps_k3_at_zero(detections):
    result = calibrate(detections, BOARD, SIZE, fix_k3=True)
    assert result.camera.dist[4] == 0.0 and "k3" not in result.std and "k1" in result.std
    assert result.notes == ["k3 fixed at 0"]


def test_poor_coverage_is_said(detections):
    from deepcharuco.calibration.views import coverage, coverage_notes as _coverage_notes

    assert coverage(detections, SIZE) > 0.5 and _coverage_notes(detections, SIZE) == []
    central = [FrameDetection(0, "c", np.arange(4), np.array([[125.0, 85], [150, 85], [125, 115], [150, 115]]))]
    assert coverage(central, SIZE) == pytest.approx(1 / 48)
    assert "cover only 2 % of the image" in _coverage_notes(central, SIZE)[0]


def test_hybrid_detector_is_offered(waved):
    from deepcharuco.cli.detect import make_detector

    detector = make_detector("hybrid", BOARD, "refinenet")
    assert detector.mode == "hybrid" and len(detector.detect(waved[0][0])) >= 8


def _exact_views(waved, noise_px=0.0, seed=0):
    """FrameDetections at the true distorted corners of the waved video (+ Gaussian noise), with true K, dist."""
    _, K, dist = waved
    rng = np.random.default_rng(seed)
    path_rng = np.random.default_rng(7)
    true_camera(path_rng, -0.3, SIZE)  # the fixture's draws, in its order
    path = WavingPath.draw(path_rng)
    frames = []
    for index, t in enumerate(frame_times(FRAMES, path_rng)):
        rvec, tvec = pose_of(hand_waved_pose(path, t, BOARD, K, dist, SIZE))
        corners = cv2.projectPoints(BOARD.object_points(), rvec, tvec, K, dist)[0].reshape(-1, 2)
        inside = (corners[:, 0] > 0) & (corners[:, 1] > 0) & (corners[:, 0] < SIZE[0] - 1) & (corners[:, 1] < SIZE[1] - 1)
        ids = np.flatnonzero(inside)
        frames.append(FrameDetection(index, str(index), ids, corners[ids] + rng.normal(0, noise_px, (len(ids), 2)), 1.0))
    return frames


def test_exact_views_recover_the_camera_exactly(waved, without_bootstrap):
    # The views, not the solver, limit the rendered sequences' accuracy: from exact corners it is exact.
    _, K, dist = waved
    result = calibrate(_exact_views(waved), BOARD, SIZE)
    np.testing.assert_allclose(result.camera.K, K, atol=1e-3)
    np.testing.assert_allclose(result.camera.dist, dist, atol=1e-4)


def test_per_corner_uncertainty_matches_the_noise(waved, without_bootstrap):
    result = calibrate(_exact_views(waved, noise_px=0.15), BOARD, SIZE)
    # The residual RMS (per axis) understates the noise: the fit absorbs part of it; corner_sigma does not.
    assert result.rms / np.sqrt(2) < result.corner_sigma
    assert result.corner_sigma == pytest.approx(0.15, rel=0.1)


def test_camera_file_holds_the_per_corner_uncertainty(tmp_path, waved, without_bootstrap):
    out = tmp_path / "camera.yaml"
    assert main([str(_video(tmp_path / "wave.avi", waved[0])), "--out", str(out), "--quiet", "--no-report"]) == 0
    storage = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    sigma = storage.getNode("corner_sigma_px").real()
    residuals = storage.getNode("corner_residuals").mat()
    frames = storage.getNode("view_frames").mat().ravel()
    weights = storage.getNode("view_weights").mat()
    storage.release()
    # drawn frames: the pattern fit's corners are ~0.01 px (sigma 0.014 px, residuals at most 0.07 px, 2026-11-27)
    assert 0.007 < sigma < 0.03 and residuals.shape[1] == 4
    assert set(residuals[:, 0].astype(int)) == set(frames.astype(int))  # one row per used corner of each view
    assert np.all(np.abs(residuals[:, 2:]) < 0.15)
    # Each view's weight (calibration.weigh_views): most views are alike and weigh fully.
    assert weights.shape == (len(frames), 1) and np.all((weights > 0) & (weights <= 1)) and np.median(weights) > 0.99
    equal = tmp_path / "equal.yaml"
    assert main([str(tmp_path / "wave.avi"), "--out", str(equal), "--quiet", "--no-report", "--equal-weights"]) == 0
    storage = cv2.FileStorage(str(equal), cv2.FILE_STORAGE_READ)
    assert storage.getNode("view_weights").empty()
    storage.release()
    assert abs(read_camera(equal).K[0, 0] / read_camera(out).K[0, 0] - 1) < 2.5e-4  # 7.6e-5 apart (2026-11-27)


def test_a_wrong_corner_at_the_edge_cannot_bend_k3(without_bootstrap):
    # The deep detector's corners on the rendered k1 = +0.1 validation sequence (evaluate.calibration.calibration_sequences,
    # seed 0, good light; the true camera stored beside them): one corner lies 17 px off at the image's edge.
    # Solved with k3 free from the start, k2 and k3 bent the edges to meet it (fx +0.7 %, cy +4 px, RMS 0.185 px);
    # judged first with k3 at 0, it is dropped and the lens recovered.
    data = np.load(ROOT / "tests" / "fixtures" / "calibration_deep_k1+0.10.npz")
    size = tuple(int(v) for v in data["size"])
    frames = [FrameDetection(i, str(i), data["ids"][data["frame"] == i], data["corners"][data["frame"] == i],
                             float(data["sharpness"][i])) for i in range(len(data["sharpness"]))]
    result = calibrate(frames, BOARD, size)
    K = data["K"]
    assert "outlier corner(s) dropped" in {d.index: d for d in result.decisions}[14].reason
    assert abs(result.camera.K[0, 0] / K[0, 0] - 1) < 0.003 and abs(result.camera.K[1, 1] / K[1, 1] - 1) < 0.003
    assert np.abs(result.camera.K[:2, 2] - K[:2, 2]).max() < 1.5 and result.rms < 0.14
    assert abs(result.camera.dist[0] - data["dist"][0]) < 0.02


def test_corners_at_the_border_are_left_out_for_refinenet():
    from deepcharuco.calibration.views import border_margin, within_border

    assert border_margin("refinenet") == 12.0 and border_margin("subpix") == 0.0
    frame = FrameDetection(3, "f", np.arange(4), np.array([[5.0, 100], [12.0, 100], [160, 120], [310.0, 234]]))
    kept = within_border(frame, SIZE, 12.0)
    assert kept.ids.tolist() == [1, 2] and within_border(frame, SIZE, 0.0) is frame


def test_all_corners_along_one_line_says_show_more_of_the_board():
    row = np.stack([np.arange(4) * 30.0 + 50, np.full(4, 100.0)], 1)
    frames = [FrameDetection(i, str(i), np.arange(4), row + i * 5.0) for i in range(8)]
    with pytest.raises(CalibrationError, match="8 frame\\(s\\) show only one row or column of corners"):
        calibrate(frames, BOARD, SIZE, options=SelectionOptions(min_corners=4))


def test_one_pose_over_and_over_says_move_the_board(tmp_path, capsys, waved):
    message = _fail(tmp_path, capsys, [waved[0][5]] * 10)
    assert "only 1 usable view(s)" in message and "repeat a pose already kept" in message
    assert "move and tilt the board" in message


def test_camera_files_name_their_model(tmp_path):
    from deepcharuco.core.errors import CameraFileError

    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    for model, count, expected in (("rational", 8, "pinhole"), ("pinhole", 5, "pinhole"), ("fisheye", 4, "fisheye")):
        storage = cv2.FileStorage(str(tmp_path / f"{model}.yaml"), cv2.FILE_STORAGE_WRITE)
        for name, value in (("image_width", 320), ("image_height", 240), ("camera_matrix", K),
                            ("distortion_coefficients", np.full((count, 1), 0.01)), ("distortion_model", model)):
            storage.write(name, value)
        storage.release()
        camera = read_camera(tmp_path / f"{model}.yaml")
        assert camera.model == expected and camera.dist.shape == (count,)
    storage = cv2.FileStorage(str(tmp_path / "other.yaml"), cv2.FILE_STORAGE_WRITE)
    for name, value in (("image_width", 320), ("image_height", 240), ("camera_matrix", K), ("distortion_model", "kb8")):
        storage.write(name, value)
    storage.release()
    with pytest.raises(CameraFileError, match="distortion_model 'kb8'"):
        read_camera(tmp_path / "other.yaml")
    with pytest.raises(CameraFileError, match="fisheye camera has 4 distortion coefficients"):
        Camera(K=K, dist=np.zeros(5), image_size=(320, 240), model="fisheye")


def test_a_distortion_model_that_folds_inside_the_image_is_found():
    """fold_share: a lens maps radius to radius one to one out to the corners; k3 = -1.20 (a real webcam's solve from
    views that left the corners empty) folds two thirds of the way out; k2 < 0 alone folds near the corners."""
    from deepcharuco.calibration.intrinsics import fold_share

    K = np.array([[750.0, 0, 640], [0, 750, 360], [0, 0, 1]])
    folds = {k: fold_share(Camera(K=K, dist=np.array(d, float), image_size=(1280, 720))) for k, d in {
        "none": [0, 0, 0, 0, 0], "barrel": [-0.3, 0.09, 0, 0, 0], "caliscope": [0.099, -0.22, 0, -0.003, 0.081],
        "k3": [0.042, 0.12, 0, 0, -1.20], "k2": [0.08, -0.2, 0, 0, 0.03]}.items()}
    assert folds["none"] is None and folds["barrel"] is None and folds["caliscope"] is None
    assert 0.6 < folds["k3"] < 0.7 and 0.95 < folds["k2"] < 1.0


def test_a_fold_inside_the_image_is_solved_again_without_k3_or_refused(detections, monkeypatch, without_bootstrap):
    import deepcharuco.calibration.intrinsics as calibration

    shares = iter([0.6, None])
    monkeypatch.setattr(calibration, "fold_share", lambda camera: next(shares))
    result = calibrate(detections, BOARD, SIZE)
    assert result.notes[0].startswith("with k3 free the solved distortion folds back 60 %")
    assert "k3 fixed at 0" in result.notes and result.terms.split()[-1] != "k3"
    monkeypatch.setattr(calibration, "fold_share", lambda camera: 0.6)
    with pytest.raises(CalibrationError, match="folds back 60 % .* capture the board near the image's edges"):
        calibrate(detections, BOARD, SIZE, fix_k3=True)
    monkeypatch.setattr(calibration, "fold_share", lambda camera: 0.97)
    assert any("folds back 97 %" in note for note in calibrate(detections, BOARD, SIZE).notes)


def test_deviations_are_at_least_the_view_bootstrap_spread(calibrated):
    from deepcharuco.calibration.terms import bootstrap_std

    result, ((args, kwargs), spread) = calibrated  # the bootstrap calibrate ran: of its kept views, with its terms
    objects = [BOARD.object_points()[v.ids] for v in result.views]
    images = [v.corners for v in result.views]
    assert not kwargs and args[2:5] == (SIZE, "pinhole", result.terms) and np.array_equal(args[5].K, result.camera.K)
    assert [o.tolist() for o in args[0]] == [o.tolist() for o in objects]
    assert [i.tolist() for i in args[1]] == [i.tolist() for i in images]
    solution = type("S", (), {"K": result.camera.K, "dist": result.camera.dist})()
    # seeded: the same resamples (OpenCV 5's calibrateCamera repeats itself to ~1e-9, not bit for bit); 4 rounds
    # show it as 20 do, and the second seed draws other views
    few = [bootstrap_std(objects, images, SIZE, "pinhole", result.terms, solution, rounds=4, seed=s) for s in (0, 0, 1)]
    assert few[0] == pytest.approx(few[1], rel=1e-6) and few[0] != pytest.approx(few[2], rel=1e-3)
    assert set(spread) >= {"fx", "fy", "cx", "cy", "k1"}
    for name, value in spread.items():
        assert result.std[name] >= value * (1 - 1e-6)  # the larger of the solver's and the bootstrap's
        assert 0 < value < 20 * result.std[name]


def test_network_fast_with_weights_is_refused_in_one_line(tmp_path, capsys, waved):
    video = _video(tmp_path / "waved.avi", waved[0][:6])
    out = tmp_path / "camera.yaml"
    code = main([str(video), "--out", str(out), "--quiet", "--network", "fast", "--weights", "mine.pt"])
    message = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and not out.exists() and len(message) == 1
    assert "give weights or network='fast', not both" in message[0]
