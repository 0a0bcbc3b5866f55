import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import VIEW_POSES, make_view
from deepcharuco import BoardSpec, write_camera
from deepcharuco.detect import main
from deepcharuco.examples.make_examples import make_example

EXAMPLES = Path(__file__).parents[1] / "deepcharuco" / "examples"


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
    assert frame["pose"]["reprojection_error"] < 0.3
    assert (tmp_path / "board_320x240_overlay.png").is_file()
    rows = (tmp_path / "board_320x240.csv").read_text().splitlines()
    assert len(rows) == 2 and rows[1].startswith("0,board_320x240.png,16,0 1 2")


def test_video_and_scaled_camera(tmp_path, camera):
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
        (["--refine", "refinenet"], "needs --detector deep"),
        (["--camera", "missing.yaml"], "camera file missing.yaml does not exist"),
        (["--board", "missing.json"], "board file missing.json does not exist"),
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
    assert "default: opencv" in result.stdout and "default: detect_out" in result.stdout
