"""RefineNet started on a second thread while a board's markers are read (`levels.EarlyRefinement`)."""

import multiprocessing

import numpy as np
import pytest

from conftest import VIEW_POSES, make_view
from deepcharuco import BoardSpec
from deepcharuco.detection.deep_detector import Detector
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
