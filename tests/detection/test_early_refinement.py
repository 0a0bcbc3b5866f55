"""RefineNet started on a second thread while a board's markers are read (`levels.EarlyRefinement`), and a level's
corners refined once, at full resolution, where that is enough (`deep_detector.ONE_PASS_MAX_RATIO`)."""

import multiprocessing

import numpy as np
import pytest

from conftest import VIEW_POSES, make_view
import deepcharuco.detection.deep_detector as deep_detector
from deepcharuco import BoardSpec
from deepcharuco.core.detection import Detection
from deepcharuco.core.stage_times import StageTimes
from deepcharuco.detection.deep_detector import Detector
from deepcharuco.geometry.camera import Camera
from deepcharuco.networks.runtime import BackgroundThread, onnxruntime_available

BOARD = BoardSpec(squares_x=7, squares_y=5, square_length=0.04, marker_length=0.03, dictionary="DICT_6X6_250")


@pytest.mark.skipif(not onnxruntime_available(), reason="ONNX Runtime not installed")
def test_early_refinement_gives_the_corners_refinenet_gives_after_the_search(camera, torch_threads):
    torch_threads(2)  # the runners take ONNX Runtime's threads from torch; one thread in all has no background
    early = Detector(board=BOARD, backend="onnx")
    late = Detector(board=BOARD, backend="onnx")
    late.runner.refinenet_in_background = lambda patches: None  # RefineNet after the marker search only
    patches_now = []
    run = early.runner.refinenet
    early.runner.refinenet = lambda patches: patches_now.append(len(patches)) or run(patches)
    found = 0
    for pose in VIEW_POSES:
        image = make_view(BOARD, camera, **pose)[0]
        a, b = early.detect(image), late.detect(image)
        np.testing.assert_array_equal(a.ids, b.ids)
        np.testing.assert_array_equal(a.corners, b.corners)
        found += len(a)
    assert found >= 60
    # Most corners came from the early run: RefineNet ran afterwards only for the few that were not in it.
    assert sum(patches_now) < found / 4


def _submit_in_child(background, queue):
    queue.put(background.submit(lambda: 41 + 1).result(timeout=20))


@pytest.mark.skipif("fork" not in multiprocessing.get_all_start_methods(), reason="no fork on this platform")
def test_background_thread_works_in_a_forked_child():
    background = BackgroundThread()
    assert background.submit(lambda: 7).result(timeout=20) == 7  # the parent's thread exists before the fork
    context = multiprocessing.get_context("fork")
    queue = context.Queue()
    child = context.Process(target=_submit_in_child, args=(background, queue))
    child.start()
    child.join(60)
    assert child.exitcode == 0 and queue.get(timeout=5) == 42


@pytest.mark.skipif(not onnxruntime_available(), reason="ONNX Runtime not installed")
def test_a_level_half_the_frames_size_is_refined_once_at_full_resolution(torch_threads, monkeypatch):
    """A 640x480 view found at the 320-px level: where the printed-pattern fit follows, RefineNet refines each corner
    once, at full resolution from its cell pixel (`ONE_PASS_MAX_RATIO`), and nothing early at the level, and the
    fitted corners are those of two passes; without the fit, at the level and again at full resolution."""
    torch_threads(2)
    camera = Camera.from_fov(640, 480, hfov_deg=60.0)
    image, _, _, truth = make_view(BOARD, camera, distance=0.5, tilt_y_deg=30, roll_deg=20)  # squares ~22 px at 320

    def detect(corner_fit: bool) -> tuple[Detection, list[int]]:
        detector = Detector(board=BOARD, backend="onnx", corner_fit=corner_fit)
        patches = []
        run, run_early = detector.runner.refinenet, detector.runner.refinenet_in_background
        detector.runner.refinenet = lambda batch: patches.append(len(batch)) or run(batch)
        detector.runner.refinenet_in_background = lambda batch: patches.append(len(batch)) or run_early(batch)
        with StageTimes() as times:
            found = detector.detect(image)
        assert len(found) == BOARD.num_corners
        assert times.counts["network 0"] == 1 and times.counts["network 1"] == 0  # found at 320 px
        return found, patches

    once, patches = detect(corner_fit=True)
    assert patches == [BOARD.num_corners]
    assert np.abs(once.corners - truth[once.ids]).max() < 0.03
    assert sum(detect(corner_fit=False)[1]) >= 2 * BOARD.num_corners
    monkeypatch.setattr(deep_detector, "ONE_PASS_MAX_RATIO", 0.0)
    twice, patches = detect(corner_fit=True)
    assert sum(patches) >= 2 * BOARD.num_corners
    np.testing.assert_array_equal(once.ids, twice.ids)
    np.testing.assert_allclose(once.corners, twice.corners, atol=2e-3)
