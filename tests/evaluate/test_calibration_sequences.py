"""evaluate.calibration.calibration_sequences: the waving path (plain numpy) and the rendered shards (Blender)."""

import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

from conftest import ROOT

from datagen.shards import ShardReader, list_shards
from deepcharuco import BoardSpec, OpenCVDetector
from evaluate.calibration.calibration_sequences import (
    CALIBRATION_SEQUENCES, NAMES, SWEEP_S, WavingPath, hand_waved_pose, pose_of, read_truth, true_camera,
)

BOARD = BoardSpec()
SIZE = (320, 240)
FRAMES = 3


def test_the_waving_covers_the_image_and_the_tilts():
    rng = np.random.default_rng(3)
    K, dist = true_camera(rng, -0.4, SIZE)
    path = WavingPath.draw(rng)
    centres, normals = [], []
    for t in np.linspace(0.0, SWEEP_S, 300, endpoint=False):
        transform = hand_waved_pose(path, t, BOARD, K, dist, SIZE)
        points = BOARD.object_points() @ transform[:3, :3].T + transform[:3, 3]
        assert points[:, 2].min() > 0.05  # the whole board in front of the camera
        rvec, tvec = pose_of(transform)
        centre, _ = cv2.projectPoints(np.array([[*np.array(BOARD.size_m) / 2, 0.0]]), rvec, tvec, K, dist)
        centres.append(centre.ravel())
        normals.append(transform[:3, 2])
    centres, normals = np.array(centres), np.array(normals)
    # The centre sweeps 0.32 W / 0.30 H either side of the middle; the board faces 40 degrees away each way.
    assert np.ptp(centres[:, 0]) > 0.6 * SIZE[0] and np.ptp(centres[:, 1]) > 0.55 * SIZE[1]
    assert np.degrees(np.arccos(np.clip(normals @ normals.T, -1, 1))).max() > 60.0


def test_nine_sequences_three_per_camera():
    assert len(CALIBRATION_SEQUENCES) == 9 and len(set(NAMES)) == 9
    assert [s.number for s in CALIBRATION_SEQUENCES] == list(range(9))
    assert {s.condition for s in CALIBRATION_SEQUENCES if s.camera == 0} == {"good", "1lux", "shake"}


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    pytest.importorskip("bpy", reason="the renderer needs the [render] extra (bpy)")
    out = tmp_path_factory.mktemp("calibration")
    result = subprocess.run([sys.executable, "-m", "evaluate.calibration.calibration_sequences", "--out", str(out), "--frames",
                             str(FRAMES), "--samples", "2", "--cameras", "2", "--quiet"], cwd=ROOT, capture_output=True,
                            text=True, env={**os.environ, "SOURCE_DATE_EPOCH": "1700000000"})
    assert result.returncode == 0, result.stderr[-3000:]
    return out


def frames_of(path):
    reader = ShardReader(path)
    frames = [reader[i] for i in range(len(reader))]
    reader.close()
    return frames


def test_shards_hold_the_distorted_camera_and_its_labels(rendered):
    assert [p.name for p in list_shards(rendered)] == ["shard-00006.h5", "shard-00007.h5", "shard-00008.h5"]
    good, dark, shake = (frames_of(rendered / f"shard-0000{n}.h5") for n in (6, 7, 8))
    K, dist, size = read_truth(rendered / "shard-00006.h5")
    assert size == SIZE and dist[0] == pytest.approx(0.1) and dist[1] == pytest.approx(0.01)
    assert [f.meta["sequence"] for f in good] == ["k1+0.10-good"] * FRAMES
    assert [f.meta["condition"] for f in dark] == ["1lux"] * FRAMES and dark[0].meta["lux"] == 1.0
    for g, d in zip(good, dark):  # the same renders: the same labels, another light
        np.testing.assert_array_equal(g.corners, d.corners)
        assert d.image.mean() < g.image.mean() + 10 and d.meta["gain"] > g.meta["gain"]
    assert all(f.meta["blur_px"] > 0 for f in shake) and all(f.meta["blur_px"] == 0 for f in good)
    # Labels are cv2.projectPoints with the distorted camera.
    for frame in good:
        projected, _ = cv2.projectPoints(BOARD.object_points(), frame.rvec.astype(np.float64),
                                         frame.tvec.astype(np.float64), K, dist)
        visible = frame.visible
        np.testing.assert_allclose(frame.corners[visible], projected.reshape(-1, 2)[visible], atol=1e-3)


def test_opencv_finds_the_corners_where_the_labels_are(rendered):
    detector = OpenCVDetector(BOARD)
    errors = []
    for frame in frames_of(rendered / "shard-00006.h5"):
        detection = detector.detect(frame.image)
        errors += [np.linalg.norm(c - frame.corners[i]) for i, c in zip(detection.ids, detection.corners)]
    assert len(errors) >= 8, "OpenCV should find most corners of good-light frames"
    assert np.median(errors) < 0.3


def test_conditions_choose_the_shards_and_the_renders():
    from evaluate.calibration.calibration_sequences import CONDITIONS, CalibrationJob, renders_per_camera

    common = dict(out="x", seed=0, frames=10, board=BOARD, width=320, height=240, samples=2, device="cpu", threads=1)
    full, still = CalibrationJob(**common), CalibrationJob(**common, conditions=("good", "1lux"))
    assert full.numbers([0, 2]) == [0, 1, 2, 6, 7, 8] and still.numbers([0, 2]) == [0, 1, 6, 7]
    # good light and 1 lux share their renders; shake doubles them.
    assert renders_per_camera(full) == 20 and renders_per_camera(still) == 10
    assert renders_per_camera(CalibrationJob(**common, conditions=("shake",))) == 10
    # A full run's arguments are those of runs made before the option: their shards still resume.
    assert "conditions" not in full.content() and still.content()["conditions"] == ["good", "1lux"]
    assert full.conditions == CONDITIONS
