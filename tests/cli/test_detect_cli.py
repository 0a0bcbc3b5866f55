import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from conftest import ROOT, VIEW_POSES, make_view
from deepcharuco import BoardSpec, write_camera
from deepcharuco.cli.detect import main
from deepcharuco.examples.make_examples import make_example

EXAMPLES = ROOT / "deepcharuco" / "examples"


def test_bundled_example_is_current():
    image, _ = make_example()
    shipped = cv2.imread(str(EXAMPLES / "board_320x240.png"), cv2.IMREAD_GRAYSCALE)
    # OpenCV's SIMD paths may round a grey level differently on another CPU: allow that, no more.
    difference = np.abs(shipped.astype(int) - image)
    assert difference.max() <= 2 and difference.mean() < 0.05


def test_image_with_pose(tmp_path):
    code = main([str(EXAMPLES / "board_320x240.png"), "--camera", str(EXAMPLES / "webcam_320x240.yaml"),
                 "--out", str(tmp_path)])
    assert code == 0
    result = json.loads((tmp_path / "board_320x240.json").read_text())
    frame = result["frames"][0]
    assert frame["ids"] == list(range(16)) and len(frame["corners"]) == 16
    assert frame["time_s"] is None and result["video_fps"] is None  # an image has no time
    assert frame["pose"]["reprojection_error"] < 0.3
    assert (tmp_path / "board_320x240_overlay.png").is_file()
    rows = (tmp_path / "board_320x240.csv").read_text().splitlines()
    assert len(rows) == 2 and rows[1].startswith("0,board_320x240.png,16,0 1 2")


@pytest.mark.parametrize("detector", ["deep", "hybrid", "opencv"])
def test_corner_uncertainties_in_the_csv_and_json(tmp_path, detector):
    import csv

    for fit in (True, False):
        out = tmp_path / f"{detector}-{fit}"
        extra = [] if fit else ["--no-corner-fit"]
        assert main([str(EXAMPLES / "board_320x240.png"), "--detector", detector, "--out", str(out), "--quiet",
                     *extra]) == 0
        row = next(csv.DictReader((out / "board_320x240.csv").open()))
        sigmas = np.array(row["sigmas"].split(), float)
        covariances = json.loads((out / "board_320x240.json").read_text())["frames"][0]["covariances"]
        assert len(sigmas) == len(covariances) == int(row["num_corners"]) >= 14
        if fit and detector != "opencv":  # OpenCV's corners carry none
            assert np.all((sigmas > 0.001) & (sigmas < 0.5))
            xx, xy, yy = np.array(covariances).T
            assert np.allclose(sigmas ** 2, (xx + yy) / 2 + np.hypot((xx - yy) / 2, xy), rtol=1e-3, atol=1e-6)
        else:
            assert np.all(np.isnan(sigmas)) and all(c is None for c in covariances)


def test_video_and_scaled_camera(tmp_path, camera, capsys):
    board = BoardSpec()
    video = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (320, 240))
    for pose in VIEW_POSES[:3]:
        writer.write(cv2.cvtColor(make_view(board, camera, **pose)[0], cv2.COLOR_GRAY2BGR))
    writer.write(np.full((240, 320, 3), 128, np.uint8))  # a frame without the board
    writer.release()
    write_camera(tmp_path / "cam640.yaml", camera.scaled(640, 480))  # calibrated at another resolution
    out = tmp_path / "out"
    assert main([str(video), "--camera", str(tmp_path / "cam640.yaml"), "--out", str(out), "--quiet"]) == 0
    frames = json.loads((out / "clip.json").read_text())["frames"]
    assert [f["num_corners"] for f in frames] == [16, 16, 16, 0]
    assert all(f["pose"]["reprojection_error"] < 0.5 for f in frames[:3]) and frames[3]["pose"] is None
    assert (out / "clip_overlay.mp4").stat().st_size > 0
    assert len((out / "clip.csv").read_text().splitlines()) == 5
    # Each frame's time in the recording (30 fps as written), in the JSON and the CSV; the container's frame rate.
    result = json.loads((out / "clip.json").read_text())
    assert [f["time_s"] for f in result["frames"]] == pytest.approx([0, 1 / 30, 2 / 30, 3 / 30], abs=1e-6)
    assert result["video_fps"] == pytest.approx(30.0)
    rows = (out / "clip.csv").read_text().splitlines()
    assert rows[0].endswith(",sigmas,time_s") and rows[2].endswith(",0.033333")
    # The scaling is said once, and recorded beside the file's own intrinsics.
    err = capsys.readouterr().err
    assert err.count("is for 640x480 and 0 is 320x240: its intrinsics are scaled to it") == 1
    recorded = json.loads((out / "clip.json").read_text())["camera"]
    assert recorded["image_size"] == [640, 480] and recorded["scaled_to"] == [[320, 240]]
    assert recorded["model"] == "pinhole"


def test_folder_of_images_without_camera(tmp_path, camera, default_views):
    folder = tmp_path / "imgs"
    folder.mkdir()
    for i, (image, *_rest) in enumerate(default_views[:2]):
        cv2.imwrite(str(folder / f"{i:03d}.png"), image)
    (folder / "notes.txt").write_text("not an image")
    assert main([str(folder), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    frames = json.loads((tmp_path / "out" / "imgs.json").read_text())["frames"]
    assert [f["source"] for f in frames] == ["000.png", "001.png"]
    assert all(f["pose"] is None and f["num_corners"] == 16 for f in frames)
    assert sorted(p.name for p in (tmp_path / "out" / "imgs_overlay").iterdir()) == ["000.png", "001.png"]


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--detector", "deep", "--weights", "missing.pt"], "weights file missing.pt does not exist"),
        (["--detector", "opencv", "--refine", "refinenet"], "needs --detector deep"),
        (["--camera", "missing.yaml"], "camera file missing.yaml does not exist"),
        (["--board", "missing.json"], "board file missing.json does not exist"),
        (["--network", "fast", "--weights", "mine.pt"], "give weights or network='fast', not both"),
        (["--network", "fast", "--device", "cuda"], "run on the CPU"),
        (["--network", "auto", "--weights", "mine.pt"], "give weights or network='auto', not both"),
    ],
)
def test_clear_errors(tmp_path, capsys, extra, message):
    code = main([str(EXAMPLES / "board_320x240.png"), "--out", str(tmp_path), *extra])
    assert code == 2
    assert message in capsys.readouterr().err


def test_unreadable_sources(tmp_path, capsys):
    assert main([str(tmp_path / "nothing.png"), "--out", str(tmp_path)]) == 2
    assert "does not exist" in capsys.readouterr().err
    (tmp_path / "broken.png").write_bytes(b"not a png")
    assert main([str(tmp_path / "broken.png"), "--out", str(tmp_path)]) == 2
    assert "cannot read image" in capsys.readouterr().err


def test_help_shows_defaults():
    result = subprocess.run([sys.executable, "-m", "deepcharuco.detect", "--help"], capture_output=True, text=True)
    assert result.returncode == 0
    assert "hybrid (the default)" in result.stdout and "default: detect_out" in result.stdout


def test_a_folder_with_an_unreadable_image_and_shared_stems(tmp_path, capsys, default_views):
    """An unreadable image is skipped, said and counted; a.png and a.jpg get an overlay each."""
    folder = tmp_path / "imgs"
    folder.mkdir()
    cv2.imwrite(str(folder / "a.png"), default_views[0][0])
    cv2.imwrite(str(folder / "a.jpg"), default_views[1][0])
    (folder / "b.png").write_bytes(b"\x89PNG cut short")
    cv2.imwrite(str(folder / "c.png"), default_views[2][0])
    assert main([str(folder), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "skipping b.png: cannot read image" in captured.err and "1 image(s) skipped (each named above)" in captured.out
    result = json.loads((tmp_path / "out" / "imgs.json").read_text())
    assert [f["source"] for f in result["frames"]] == ["a.jpg", "a.png", "c.png"]
    assert len(result["skipped"]) == 1 and result["skipped"][0].startswith("b.png: ")
    overlays = tmp_path / "out" / "imgs_overlay"
    assert sorted(p.name for p in overlays.iterdir()) == ["a_jpg.png", "a_png.png", "c.png"]
    assert not np.array_equal(cv2.imread(str(overlays / "a_jpg.png")), cv2.imread(str(overlays / "a_png.png")))


def test_a_full_disk_is_an_error_not_a_success(tmp_path):
    """cv2.imwrite answers a failed write with False only; a file-size limit makes the overlay's write fail
    (the CSV and JSON, a few hundred bytes, still fit)."""
    import resource

    limit = 8_000  # bytes; the overlay PNG is ~100 kB
    done = subprocess.run([sys.executable, "-m", "deepcharuco.detect", str(EXAMPLES / "board_320x240.png"), "--out",
                           str(tmp_path), "--quiet"], capture_output=True, text=True,
                          preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit)))
    assert done.returncode == 2, done.stderr
    assert "could not write the overlay" in done.stderr and "Traceback" not in done.stderr


def test_unwritable_or_file_out(tmp_path, capsys, unwritable_dir):
    (tmp_path / "a-file").write_text("")
    for out, message in ((tmp_path / "a-file", "is a file, not a folder"), (unwritable_dir / "out", "cannot write there")):
        assert main([str(EXAMPLES / "board_320x240.png"), "--out", str(out), "--quiet"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert message in err[-1] and not any("Traceback" in line for line in err)


def test_hybrid_detector_and_tracking_options(tmp_path, capsys):
    out = tmp_path / "hybrid"
    assert main([str(EXAMPLES / "board_320x240.png"), "--detector", "hybrid", "--backend", "torch",
                 "--out", str(out), "--no-overlay"]) == 0
    result = json.loads((out / "board_320x240.json").read_text())
    assert "mode='hybrid'" in result["detector"] and result["frames"][0]["num_corners"] == 16
    assert result["detect_fps"] > 0
    with pytest.raises(SystemExit):
        main([str(EXAMPLES / "board_320x240.png"), "--refresh-every", "0", "--out", str(tmp_path / "x")])
    assert "--refresh-every must be >= 1" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_code:
        main([str(EXAMPLES / "board_320x240.png"), "--search-every", "0", "--out", str(tmp_path / "x")])
    assert exit_code.value.code == 2 and "--search-every must be >= 1" in capsys.readouterr().err


def test_a_fisheye_camera_gives_the_true_pose(camera):
    """A fisheye camera file's k1..k4 are not pinhole coefficients: the pose goes through its own model."""
    from deepcharuco import OpenCVDetector
    from deepcharuco.geometry.camera import Camera

    board = BoardSpec()
    pinhole, rvec, tvec, _ = make_view(board, camera, distance=0.4, tilt_x_deg=20, offset=(0.04, 0.02))
    fisheye = Camera(K=camera.K, dist=np.array([0.08, 0.02, 0.0, 0.0]), image_size=camera.image_size, model="fisheye")
    # The fisheye image: each of its pixels shows what the pinhole view shows where that pixel undistorts to.
    xs, ys = np.meshgrid(np.arange(320, dtype=np.float64), np.arange(240, dtype=np.float64))
    source = fisheye.undistort_points(np.stack([xs.ravel(), ys.ravel()], axis=1)).astype(np.float32).reshape(240, 320, 2)
    image = cv2.remap(pinhole, source[..., 0], source[..., 1], cv2.INTER_LINEAR, borderValue=90)
    detector = OpenCVDetector(board, refine="subpix")
    detection = detector.detect(image)
    assert len(detection) >= 12
    pose = detector.estimate_pose(detection, fisheye)  # as detect poses a frame: the Camera, its model
    assert np.linalg.norm(pose.tvec.ravel() - tvec.ravel()) < 0.005 * np.linalg.norm(tvec)
    naive = detector.estimate_pose(detection, fisheye.K, fisheye.dist)  # k1..k4 read as k1 k2 p1 p2
    assert naive is None or np.linalg.norm(naive.tvec.ravel() - tvec.ravel()) > 2 * np.linalg.norm(pose.tvec.ravel() - tvec.ravel())
    # A fisheye file that does not say so reads as pinhole k1 k2 p1 p2: detect says that it read it so
    from deepcharuco.cli.common import four_term_note
    pinhole_four = Camera(K=camera.K, dist=fisheye.dist, image_size=camera.image_size)
    assert "add 'distortion_model: fisheye'" in four_term_note("cam.yaml", pinhole_four)
    assert four_term_note("cam.yaml", fisheye) is None and four_term_note("cam.yaml", camera) is None
    # eps_re in the frame's pixels, through the fisheye model (it was measured in the undistorted image)
    reprojected = fisheye.project(board.object_points()[detection.ids], pose.rvec, pose.tvec)
    assert pose.reprojection_error == pytest.approx(np.linalg.norm(reprojected - detection.corners, axis=1).mean())
    assert pose.reprojection_error < 0.3
    # the overlay's axes through the fisheye model: the x axis (red) ends where the fisheye projection puts it
    from deepcharuco.cli.draw import draw_detection
    end = fisheye.project(np.array([[1.5 * board.square_length, 0.0, 0.0]]), pose.rvec, pose.tvec)[0]
    canvas = draw_detection(image, detection, pose, fisheye, board).astype(int)
    x, y = np.rint(end).astype(int)
    patch = canvas[y - 2:y + 3, x - 2:x + 3]
    assert (patch[..., 2] - patch[..., 1] > 100).any()  # red drawn at the axis' end


def test_no_board_in_any_frame_says_what_the_frames_show(tmp_path, camera, capsys):
    """A run that finds nothing names the board file's change that finds it, or the markers the frames show."""
    board = BoardSpec()
    image = make_view(board, camera, **VIEW_POSES[0])[0]
    cv2.imwrite(str(tmp_path / "negative.png"), 255 - image)  # the board printed white on black
    assert main([str(tmp_path / "negative.png"), "--out", str(tmp_path / "a"), "--no-overlay", "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "warning: no board corners in any of 1 frames (hybrid detector, board 5x5 DICT_5X5_50)" in err
    assert "with inverted: true OpenCV finds the board in 1 of 1 frame(s) looked at: set inverted: true in a board file" in err
    other = BoardSpec(6, 4, 0.04, 0.03, "DICT_4X4_50")
    cv2.imwrite(str(tmp_path / "other.png"), make_view(other, camera, **VIEW_POSES[0])[0])
    assert main([str(tmp_path / "other.png"), "--out", str(tmp_path / "b"), "--no-overlay", "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "no --board was given, so the 5x5 DICT_5X5_50 board was assumed; DICT_4X4 markers are in 1 of 1" in err
    assert "(IDs 0..11)" in err and "dictionary: DICT_4X4_50 or larger" in err
    result = json.loads((tmp_path / "b" / "other.json").read_text())
    assert any("DICT_4X4 markers" in line for line in result["problems"])
    cv2.imwrite(str(tmp_path / "blank.png"), np.full((240, 320), 100, np.uint8))
    assert main([str(tmp_path / "blank.png"), "--out", str(tmp_path / "c"), "--no-overlay", "--quiet"]) == 0
    assert "no markers of any dictionary OpenCV knows are in the 1 frame(s) looked at" in capsys.readouterr().err
    assert main([str(EXAMPLES / "board_320x240.png"), "--out", str(tmp_path / "d"), "--no-overlay", "--quiet"]) == 0
    assert "warning" not in capsys.readouterr().err  # found: nothing to say


def test_a_video_without_frames_is_refused_and_nothing_is_written(tmp_path, capsys):
    """A 0-frame video exited 0 with an empty CSV and JSON (calibrate refused it); now one line, exit 2, no file."""
    empty = tmp_path / "empty.avi"
    cv2.VideoWriter(str(empty), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (320, 240)).release()  # opens, 0 frames
    out = tmp_path / "out"
    assert main([str(empty), "--out", str(out), "--quiet"]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert error[-1].startswith(f"error: no frames could be read from {empty}")
    assert not out.exists() or sorted(p.name for p in out.iterdir()) == []


def test_the_fast_networks_find_the_bundled_example(tmp_path, capsys):
    """--network fast: the shipped distilled networks, named on the terminal."""
    assert main([str(EXAMPLES / "board_320x240.png"), "--out", str(tmp_path), "--detector", "deep",
                 "--network", "fast", "--quiet"]) == 0
    summary = json.loads((tmp_path / "board_320x240.json").read_text())
    assert summary["frames"][0]["num_corners"] >= 14
    assert "weights/fast/detector.onnx" in capsys.readouterr().err


def test_without_network_the_shipped_weights_run_auto_on_the_cpu_and_lite_otherwise(tmp_path, capsys):
    """No --network: "auto" (the fast networks, the lite ones behind them) with the shipped weights in ONNX Runtime on
    the CPU, named on the terminal and in the JSON; "lite" with --weights, a GPU or PyTorch's backend."""
    from deepcharuco.networks.shipped import default_network

    assert main([str(EXAMPLES / "board_320x240.png"), "--out", str(tmp_path), "--detector", "deep", "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "weights/fast/detector.onnx" in err and "the lite networks behind them: " in err
    summary = json.loads((tmp_path / "board_320x240.json").read_text())
    assert "network='auto'" in summary["detector"] and summary["frames"][0]["num_corners"] >= 14
    assert default_network(None) == "auto" and default_network(None, "cpu", "onnx") == "auto"
    assert default_network("mine.pt") == "lite" and default_network(None, "cuda") == "lite"
    assert default_network(None, "cpu", "torch") == "lite" and default_network(None, "cpu", "onnx-int8") == "lite"


def test_image_files_of_other_depths_are_read_at_eight_bits_by_the_range_they_use():
    from deepcharuco.cli.sources import SourceError, eight_bits

    rng = np.random.default_rng(0)
    full = rng.integers(0, 65536, (6, 8), dtype=np.uint16)
    full[0, 0] = 65535
    np.testing.assert_array_equal(eight_bits(full, "a"), (full >> 8).astype(np.uint8))
    twelve = rng.integers(0, 4096, (6, 8), dtype=np.uint16)  # a 12-bit sensor's data stored as it comes
    twelve[0, 0] = 4000
    np.testing.assert_array_equal(eight_bits(twelve, "a"), (twelve >> 4).astype(np.uint8))
    assert eight_bits(twelve, "a").max() == 250  # >> 8 would leave 15
    bgra = np.dstack([twelve, twelve // 2, twelve // 4, np.full_like(twelve, 65535)])  # opaque alpha: not the range
    np.testing.assert_array_equal(eight_bits(bgra, "a"), (bgra[..., :3] >> 4).astype(np.uint8))
    unit = rng.uniform(0.0, 1.0, (6, 8)).astype(np.float32)
    np.testing.assert_array_equal(eight_bits(unit, "a"), np.rint(unit * 255.0).astype(np.uint8))
    for image, message in [(unit * 300, r"values in \[15.6064, 299.163\], not \[0, 1\]"),
                           (np.where(unit > 0.5, np.nan, unit), "not finite"), (twelve.astype(np.int16), "int16 image")]:
        with pytest.raises(SourceError, match=message):
            eight_bits(image, "a.tif")


def test_a_dim_twelve_bit_image_is_read_to_its_full_precision(tmp_path, camera):
    # A machine-vision camera's 12-bit data in a 16-bit PNG, dim (its brightest value 1,000 of 4,095): read by its own
    # range, not as a 16-bit range's top 8 bits (grey levels 0-3: corners 0.17 px off, now 0.02).
    board = BoardSpec(squares_x=7, squares_y=5, square_length=0.04, marker_length=0.03, dictionary="DICT_6X6_250")
    image, _, _, truth = make_view(board, camera, **VIEW_POSES[0])
    noise = np.random.default_rng(0).normal(0.0, 2.0, image.shape)
    raw = np.clip(np.rint(image / 255.0 * 1000.0 + noise), 0, 4095).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "dim.png"), raw)
    board_file = tmp_path / "board.yaml"
    board.save(board_file)
    assert main([str(tmp_path / "dim.png"), "--board", str(board_file), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    frame = json.loads((tmp_path / "out" / "dim.json").read_text())["frames"][0]
    assert len(frame["ids"]) == board.num_corners
    error = np.abs(np.array(frame["corners"]) - truth[frame["ids"]]).max()
    assert error < 0.08, error


def test_a_folder_with_an_image_of_unknown_scale_skips_it_and_a_lone_one_is_refused(tmp_path, capsys, default_views):
    folder = tmp_path / "imgs"
    folder.mkdir()
    cv2.imwrite(str(folder / "a.png"), default_views[0][0])
    cv2.imwrite(str(folder / "b.tiff"), default_views[1][0].astype(np.float32))  # 0-255 in floats: scale unknown
    assert main([str(folder), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "skipping b.tiff: b.tiff is a float32 image with values in [" in captured.err
    assert "1 image(s) skipped (each named above)" in captured.out  # not "unreadable": it was read, its scale unknown
    result = json.loads((tmp_path / "out" / "imgs.json").read_text())
    assert [f["source"] for f in result["frames"]] == ["a.png"] and len(result["frames"][0]["ids"]) == 16
    assert main([str(folder / "b.tiff"), "--out", str(tmp_path / "lone")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: b.tiff is a float32 image") and "8- or 16-bit" in err[0]


def test_an_image_the_camera_file_does_not_fit_keeps_its_corners_without_a_pose(tmp_path, capsys, camera,
                                                                               default_views):
    folder = tmp_path / "imgs"
    folder.mkdir()
    cv2.imwrite(str(folder / "a.png"), default_views[0][0])
    cv2.imwrite(str(folder / "b.png"), cv2.resize(default_views[1][0], (320, 320)))  # another aspect ratio
    cv2.imwrite(str(folder / "c.png"), default_views[2][0])
    write_camera(tmp_path / "cam.yaml", camera)
    assert main([str(folder), "--camera", str(tmp_path / "cam.yaml"), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    result = json.loads((tmp_path / "out" / "imgs.json").read_text())
    assert [(f["source"], f["pose"] is not None) for f in result["frames"]] == [("a.png", True), ("b.png", False),
                                                                                  ("c.png", True)]
    assert len(result["frames"][1]["ids"]) >= 12
    assert len(result["problems"]) == 1 and result["problems"][0].startswith("b.png: frames are 320x320 but the camera")
    assert "warning: b.png: frames are 320x320" in capsys.readouterr().err
    # A video's frames are all one size: that is refused whole, as before (exit 2, one line).
    video = tmp_path / "v.mp4"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), 10, (320, 320))
    for _ in range(3):
        writer.write(cv2.cvtColor(cv2.resize(default_views[1][0], (320, 320)), cv2.COLOR_GRAY2BGR))
    writer.release()
    assert main([str(video), "--camera", str(tmp_path / "cam.yaml"), "--out", str(tmp_path / "v")]) == 2
    assert "the camera file is for 320x240" in capsys.readouterr().err
    assert not (tmp_path / "v").exists()  # the folder the failed run made is gone again


def test_a_board_file_in_millimetres_is_warned_of_and_poses_come_out_in_its_unit(tmp_path, capsys):
    """A board file's lengths are metres: one written in millimetres (40 for 0.04) gets a warning naming the file, and
    its pose's translation is the metres' one times 1000 (consistent, in the file's own unit)."""
    example = [str(EXAMPLES / "board_320x240.png"), "--camera", str(EXAMPLES / "webcam_320x240.yaml"), "--detector",
               "opencv", "--no-overlay"]
    translations = []
    for name, board in (("metres", BoardSpec()), ("millimetres", BoardSpec(square_length=40.0, marker_length=30.0))):
        path = tmp_path / f"{name}.yaml"
        board.save(path)
        assert main([*example, "--board", str(path), "--out", str(tmp_path / name)]) == 0
        warned = f"warning: {path}: square_length 40 m" in capsys.readouterr().err
        assert warned == (name == "millimetres")
        frame = json.loads((tmp_path / name / "board_320x240.json").read_text())["frames"][0]
        translations.append(np.array(frame["pose"]["tvec"], np.float64))
    np.testing.assert_allclose(translations[1], 1000 * translations[0], rtol=1e-3)
