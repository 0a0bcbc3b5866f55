"""Detection on worker processes (`deepcharuco.detection.parallel`, ``detect --jobs``, ``calibrate --jobs``): the same
detections as one process, in the frames' order; the OpenCV 4 / 5 calls behind `deepcharuco.core.opencv_api`."""

import json
import pickle
from functools import partial

import cv2
import numpy as np
import pytest

from conftest import VIEW_POSES, Numbered, Racing, TrackedOnly, make_view, moving_video, video
from deepcharuco import BoardSpec
from deepcharuco.cli.detect import main as detect_main
from deepcharuco.cli.detect import make_finders
from deepcharuco.core.opencv_api import fisheye_calibration_flags, undistort_points
from deepcharuco.detection.parallel import DetectorPool
from deepcharuco.detection.tracking import StreamFrames


@pytest.fixture(scope="module")
def frames(camera):
    """Views of the paper's board, with a frame without it in between."""
    views = [make_view(BoardSpec(), camera, **pose)[0] for pose in VIEW_POSES[:4]]
    return views[:2] + [np.full_like(views[0], 128)] + views[2:]


def test_a_board_spec_pickles_after_its_opencv_board_was_built():
    board = BoardSpec(7, 5, 0.03, 0.022, "DICT_6X6_250", legacy=True)
    board.cv_board()  # cached: an OpenCV object, which does not pickle
    copy = pickle.loads(pickle.dumps(board))
    assert copy == board and copy.cv_board().getLegacyPattern()
    assert np.array_equal(copy.object_points(), board.object_points())


@pytest.mark.parametrize("name", ["deep", "opencv"])
def test_workers_give_one_process_detections_in_order(frames, name):
    make = partial(make_finders, name, [BoardSpec()], "refinenet" if name == "deep" else "subpix", None, None, "auto",
                   True, "cpu", 1)
    with DetectorPool(make) as one:
        expected = [d for _, (d,) in one.detect((i, f) for i, f in enumerate(frames))]
    with DetectorPool(make, workers=2, chunk=2) as pool:
        got = list(pool.detect((i, f) for i, f in enumerate(frames)))
        assert [key for key, _ in got] == list(range(len(frames)))
        again = [d for _, (d,) in pool.detect((i, f) for i, f in enumerate(frames[:2]))]  # the workers stay
    assert [len(d) >= 15 for d in expected] == [True, True, False, True, True] and len(expected[2]) == 0
    for (_, (detection,)), reference in zip(got, expected):
        assert np.array_equal(detection.ids, reference.ids)
        assert np.allclose(detection.corners, reference.corners, atol=1e-4)
    assert all(np.array_equal(a.ids, b.ids) for a, b in zip(again, expected))


def test_workers_track_with_the_search_they_are_given():
    deep = make_finders("deep", [BoardSpec()], "refinenet", None, None, "auto", True, "cpu", 30, 3)[0]
    assert deep.refresh_every == 30 and deep.search_every == 3
    opencv = make_finders("opencv", [BoardSpec()], "subpix", None, None, "auto", True, "cpu", 30, 3)[0]
    assert opencv.search_every == 1  # OpenCV's detector searches whole frames: nothing coarser to fall back on
    whole = make_finders("deep", [BoardSpec()], "refinenet", None, None, "auto", True, "cpu", 1, 3)[0]
    assert not hasattr(whole, "search_every")  # --refresh-every 1 (or a camera on --jobs workers): no tracker at all
    assert isinstance(whole, StreamFrames)  # but a stream's frames: the fast networks' lite backup left out


def test_pool_arguments_are_checked():
    with pytest.raises(ValueError, match="workers and chunk must be >= 1"):
        DetectorPool(list, workers=0)


def test_detect_with_jobs_writes_what_one_process_writes(tmp_path, frames):
    video = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (frames[0].shape[1], frames[0].shape[0]))
    for frame in frames:
        writer.write(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR))
    writer.release()
    results = {}
    for jobs in (1, 2):
        out = tmp_path / f"jobs{jobs}"
        # --refresh-every 1: every frame searched whole, so that chunks tracked from their first frame change nothing
        assert detect_main([str(video), "--out", str(out), "--quiet", "--detector", "deep", "--jobs", str(jobs),
                            "--refresh-every", "1", "--no-overlay"]) == 0
        results[jobs] = json.loads((out / "clip.json").read_text())
    assert [f["num_corners"] >= 15 for f in results[2]["frames"]] == [True, True, False, True, True]
    for a, b in zip(results[1]["frames"], results[2]["frames"]):
        assert a["frame"] == b["frame"] and a["ids"] == b["ids"]
        assert np.allclose(np.array(a["corners"], float).reshape(-1, 2), np.array(b["corners"], float).reshape(-1, 2),
                           atol=1e-3)
    assert results[2]["detect_fps"] > 0


@pytest.mark.parametrize("command", ["detect", "calibrate"])
def test_jobs_below_one_is_a_clear_error(tmp_path, capsys, command):
    if command == "detect":
        from deepcharuco.cli.detect import main
    else:
        from deepcharuco.cli.calibrate import main
    with pytest.raises(SystemExit) as stop:
        main([str(tmp_path / "clip.avi"), "--out", str(tmp_path / "out.yaml"), "--jobs", "0"])
    assert stop.value.code == 2 and "--jobs must be >= 1" in capsys.readouterr().err


def test_undistort_points_inverts_the_projection(camera):
    K, dist = camera.K, np.array([-0.28, 0.09, 0.001, -0.002, 0.0])
    rays = np.random.default_rng(0).uniform(-0.5, 0.5, (40, 1, 2))
    pixels, _ = cv2.projectPoints(np.concatenate([rays, np.ones((40, 1, 1))], axis=2), np.zeros(3), np.zeros(3), K, dist)
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    assert np.allclose(undistort_points(pixels, K, dist, None, criteria), rays, atol=1e-9)
    ideal = undistort_points(pixels, K, dist, K, criteria).reshape(-1, 2)
    assert np.allclose(ideal, rays.reshape(-1, 2) * [K[0, 0], K[1, 1]] + K[:2, 2], atol=1e-6)


def test_fisheye_flags_recompute_the_poses_and_fix_the_skew():
    flags = fisheye_calibration_flags()
    if hasattr(cv2.fisheye, "CALIB_FIX_SKEW"):
        assert flags == cv2.fisheye.CALIB_RECOMPUTE_EXTRINSIC | cv2.fisheye.CALIB_FIX_SKEW
    else:
        assert flags == cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW


def test_a_pool_answers_every_frame_in_order_when_a_tracker_looks_back(monkeypatch):
    from deepcharuco.detection import parallel
    from deepcharuco.detection.tracking import BoardTracker

    frames = video(10)
    present = {4, 5, 6, 7}
    # In this process: a tracker that holds frames back beside a detector that answers each at once.
    with DetectorPool(lambda: [BoardTracker(Numbered(present), search_every=3), Numbered(present)]) as pool:
        results = list(pool.detect((n, frame) for n, frame in enumerate(frames)))
    assert [key for key, _ in results] == list(range(10))
    assert [n for n, (tracked, _) in results if len(tracked) >= 4] == [4, 5, 6, 7]
    assert [n for n, (_, whole) in results if len(whole) >= 4] == [4, 5, 6, 7]
    # A worker's chunk: the same, the held frames flushed at the chunk's end.
    monkeypatch.setattr(parallel, "_finders", [BoardTracker(Numbered(present), search_every=3)])
    chunk = parallel._detect_chunk(frames[:5])  # frame 4 is held at the chunk's end: flushed, not lost
    assert len(chunk) == 5 and all(len(row) == 1 for row in chunk)
    assert [n for n, (d,) in enumerate(chunk) if len(d) >= 4] == []


def tracked_only_finders():
    from deepcharuco.detection.tracking import BoardTracker

    return [BoardTracker(TrackedOnly(), search_every=3), TrackedOnly()]


def test_workers_carry_a_tracked_board_from_one_chunk_into_the_next():
    frames = video(25)
    with DetectorPool(tracked_only_finders) as pool:
        one = list(pool.detect(enumerate(frames)))
    assert [n for n, (tracked, _) in one if len(tracked) >= 4] == list(range(1, 21))
    assert [n for n, (_, whole) in one if len(whole) >= 4] == [1]
    with DetectorPool(tracked_only_finders, workers=2, chunk=4) as pool:
        chunked = list(pool.detect(enumerate(frames)))
    # each chunk of 4 starts with a whole-frame search, which finds nothing after frame 1: the chunk is tracked
    # again from the board the chunk before ended on, as one process tracks it
    assert [n for n, _ in chunked] == list(range(25))
    assert [n for n, (tracked, _) in chunked if len(tracked) >= 4] == list(range(1, 21))
    assert [n for n, (_, whole) in chunked if len(whole) >= 4] == [1]  # a detector that does not track: as it was
    for (_, a), (_, b) in zip(one, chunked):
        np.testing.assert_array_equal(a[0].corners, b[0].corners)


def racing_finders():
    from deepcharuco.detection.tracking import BoardTracker

    return [BoardTracker(Racing())]


def test_workers_carry_a_tracked_boards_motion_from_one_chunk_into_the_next():
    # Found whole in frames 0 and 1 only, and in a crop only where the crop expects it moved on: each chunk of 4 after
    # the first is tracked again from the two frames before it, as one process tracks it.
    frames = moving_video(12)
    with DetectorPool(racing_finders) as pool:
        one = list(pool.detect(enumerate(frames)))
    with DetectorPool(racing_finders, workers=2, chunk=4) as pool:
        chunked = list(pool.detect(enumerate(frames)))
    assert [len(d) for _, (d,) in one] == [len(d) for _, (d,) in chunked] == [5] * 12
    for (_, (a,)), (_, (b,)) in zip(one, chunked):
        np.testing.assert_array_equal(a.corners, b.corners)
