"""The paper's auto-labelling recipe (evaluate.paper.autolabel): exact synthetic captures, its refusals,
and a rendered sequence compared with the render truth (one Blender render in a subprocess)."""

import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

from conftest import ROOT

from datagen.shards import ShardReader, list_shards
from deepcharuco import BoardSpec, Camera, project_corners, write_camera
from deepcharuco.boards.synthetic import look_at_pose, render_board_view
from evaluate.paper.autolabel import AutolabelError, autolabel, autolabel_sequence_errors, compare_to_truth, main

BOARD = BoardSpec()


@pytest.fixture(scope="module")
def camera_file(tmp_path_factory):
    camera = Camera.from_fov(320, 240, hfov_deg=60.0)
    return camera, write_camera(tmp_path_factory.mktemp("camera") / "webcam.yaml", camera)


def board_view(camera, **pose):
    rvec, tvec = look_at_pose(BOARD, **pose)
    image = render_board_view(BOARD, camera.K, rvec, tvec, camera.image_size)
    return image, project_corners(BOARD, rvec, tvec, camera.K), rvec, tvec


def noisy_frames(image, count, sigma=6.0, seed=0):
    rng = np.random.default_rng(seed)
    return [np.clip(np.round(image + rng.normal(0.0, sigma, image.shape)), 0, 255).astype(np.uint8) for _ in range(count)]


def write_folder(folder, frames):
    folder.mkdir(parents=True)
    for i, frame in enumerate(frames):
        cv2.imwrite(str(folder / f"frame_{i:04d}.png"), frame)
    return folder


def run_cli(*args, capsys):
    code = main([str(a) for a in args])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_image_folder_reproduces_the_true_corners(camera_file, tmp_path, capsys):
    camera, yaml = camera_file
    image, truth, rvec, tvec = board_view(camera, distance=0.33, tilt_x_deg=25, tilt_y_deg=-15, roll_deg=20)
    folder = write_folder(tmp_path / "desk", noisy_frames(image, 40))
    code, out, err = run_cli(folder, "--camera", yaml, "--out", tmp_path / "labels", "--quiet", capsys=capsys)
    assert code == 0, err
    assert "desk: 16 corners" in out
    [path] = list_shards(tmp_path / "labels")
    reader = ShardReader(path)
    assert len(reader) == 40 and reader.board == BOARD
    frames = [reader[i] for i in range(len(reader))]
    for k, frame in enumerate(frames):
        assert frame.meta["sequence"] == "desk" and frame.meta["sequence_frame"] == k and frame.meta["has_board"]
        assert frame.meta["autolabel_source"] == str(folder) and frame.meta["autolabel_corners"] == 16
        np.testing.assert_array_equal(frame.corners, frames[0].corners)
    errors = np.linalg.norm(frames[0].corners - truth, axis=1)
    assert frames[0].visible.all() and np.median(errors) < 0.08 and errors.max() < 0.25, errors
    assert np.linalg.norm(frames[0].tvec - tvec) < 1e-3  # the pose too (m)
    np.testing.assert_allclose(frames[0].K, camera.K, rtol=1e-6)
    # Refuses to overwrite, and to label the same capture twice into a folder.
    code, _, err = run_cli(folder, "--camera", yaml, "--out", tmp_path / "labels", "--index", 0, "--quiet", capsys=capsys)
    assert code == 2 and "already holds shard-00000.h5" in err
    code, _, err = run_cli(folder, "--camera", yaml, "--out", tmp_path / "labels", "--quiet", capsys=capsys)
    assert code == 2 and "already holds sequence 'desk'" in err


def test_refuses_a_short_capture(camera_file, tmp_path, capsys):
    camera, yaml = camera_file
    image, *_ = board_view(camera, distance=0.35)
    folder = write_folder(tmp_path / "short", noisy_frames(image, 12))
    code, _, err = run_cli(folder, "--camera", yaml, "--out", tmp_path / "out", capsys=capsys)
    assert code == 2 and "has 12 frames" in err and "30" in err
    assert not (tmp_path / "out").exists()


def test_refuses_a_video_without_the_board(camera_file, tmp_path, capsys):
    _, yaml = camera_file
    video = tmp_path / "blank.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (320, 240))
    assert writer.isOpened(), "this OpenCV cannot write MJPG AVI"
    rng = np.random.default_rng(1)
    for _ in range(35):
        writer.write(np.clip(128 + rng.normal(0, 4, (240, 320, 3)), 0, 255).astype(np.uint8))
    writer.release()
    code, _, err = run_cli(video, "--camera", yaml, "--out", tmp_path / "out", capsys=capsys)
    assert code == 2 and "finds 0 board corner(s) in the average" in err, err
    assert not (tmp_path / "out").exists()
    code, _, err = run_cli(video, "--out", tmp_path / "out", capsys=capsys)  # a video needs intrinsics
    assert code == 2 and "--camera" in err


def test_refuses_a_board_that_moves(camera_file, tmp_path, capsys):
    camera, yaml = camera_file
    image, *_ = board_view(camera, distance=0.35, tilt_x_deg=10)
    # Drifting right by a pixel every 6 frames: 0..5 px over the 30 averaged frames.
    frames = [np.roll(frame, k // 6, axis=1) for k, frame in enumerate(noisy_frames(image, 35, sigma=3.0))]
    folder = write_folder(tmp_path / "drift", frames)
    code, _, err = run_cli(folder, "--camera", yaml, "--out", tmp_path / "out", capsys=capsys)
    assert code == 2 and "the board moves by" in err, err
    moved = float(err.split("moves by ")[1].split(" px")[0])
    assert 1.5 < moved < 3.5  # ~2.5 px from the average's position at either end
    assert not (tmp_path / "out").exists()
    # The same frames pass when told to tolerate it, and a still board passes the default.
    code, _, err = run_cli(folder, "--camera", yaml, "--out", tmp_path / "out", "--max-motion", 4, "--quiet", capsys=capsys)
    assert code == 0, err


def test_function_refusals_and_still_board_motion(camera_file):
    camera, _ = camera_file
    image, truth, *_ = board_view(camera, distance=0.35)
    frames = np.stack(noisy_frames(image, 30))
    labels = autolabel(frames, camera.K, board=BOARD)
    assert labels.motion_px < 0.2 and labels.checked_frames == 30 and labels.reprojection_error < 0.1
    with pytest.raises(AutolabelError, match="has 29 frames"):
        autolabel(frames[:29], camera.K)
    with pytest.raises(AutolabelError, match="uint8"):
        autolabel(frames.astype(np.float32), camera.K)


@pytest.fixture(scope="module")
def rendered_sequence(tmp_path_factory):
    pytest.importorskip("bpy", reason="the renderer needs the [render] extra (bpy)")
    out = tmp_path_factory.mktemp("sequence")
    result = subprocess.run([sys.executable, "-m", "evaluate.paper.sequences", "--only", "lux-10-a", "--frames", "34",
                             "--samples", "2", "--out", str(out), "--quiet"], cwd=ROOT, capture_output=True, text=True,
                            env={**os.environ, "SOURCE_DATE_EPOCH": "1700000000"})
    assert result.returncode == 0, result.stderr[-3000:]
    [path] = list_shards(out)
    return path


def test_autolabel_of_a_rendered_sequence_matches_the_truth(rendered_sequence, tmp_path, capsys):
    code, out, err = run_cli(rendered_sequence, "--out", tmp_path / "labels", "--quiet", capsys=capsys)
    assert code == 0, err
    assert "lux-10-a:" in out and "against the render truth" in out
    [path] = list_shards(tmp_path / "labels")
    assert path.name == rendered_sequence.name  # a shard input keeps its index
    frame = ShardReader(path)[33]
    assert frame.meta["sequence"] == "lux-10-a" and frame.meta["lux"] == 10.0  # the render's meta carried over
    comparison = compare_to_truth(path, rendered_sequence)
    summary = comparison.summary()
    assert summary["frames"] == 34 and summary["corners"] >= 34 * 12
    assert summary["median_px"] < 0.3 and summary["max_px"] < 1.0, summary
    assert summary["rotation_deg_max"] < 1.0 and summary["translation_rel_max"] < 0.01, summary
    pooled = autolabel_sequence_errors(rendered_sequence.parent, BOARD, quiet=True)
    assert pooled["sequences"] == 1 and pooled["median_px"] == pytest.approx(summary["median_px"])
    assert pooled["by_condition"]["lux"]["corners"] == summary["corners"] and not pooled["refused"]
    code, _, err = run_cli(rendered_sequence, "--out", rendered_sequence.parent, capsys=capsys)
    assert code == 2 and "mix with the render truth" in err
