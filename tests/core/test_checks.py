"""One check for options and one for shapes (deepcharuco.core.checks), and the public functions that use them."""

import numpy as np
import pytest

from deepcharuco import BoardSpec, Detection, OpenCVDetector, OptionError, estimate_pose
from deepcharuco.core.checks import check_choice, check_shape
from deepcharuco.core.errors import DeepCharucoError, ShapeError


def test_a_choice_outside_the_options_names_them_all():
    assert check_choice("mode", "deep", ("deep", "hybrid")) == "deep"
    with pytest.raises(OptionError, match=r"^mode must be one of \('deep', 'hybrid'\), got 'dep'$") as caught:
        check_choice("mode", "dep", ("deep", "hybrid"))
    assert isinstance(caught.value, DeepCharucoError) and isinstance(caught.value, ValueError)


def test_a_shape_check_names_what_it_wanted_and_what_it_got():
    assert check_shape(np.eye(3), (3, 3), "K").dtype == np.float64
    assert check_shape([1, 2, 3, 4, 5], (None,), "dist").shape == (5,)
    with pytest.raises(ShapeError, match=r"^K must have shape \(3, 3\), got \(2, 3\)$"):
        check_shape(np.ones((2, 3)), (3, 3), "K")
    with pytest.raises(ShapeError, match=r"^dist must have shape \(N,\), got \(1, 5\)$"):
        check_shape(np.ones((1, 5)), (None,), "dist")
    with pytest.raises(ShapeError, match="NaN or infinite"):
        check_shape([[np.nan, 0, 0], [0, 1, 0], [0, 0, 1]], (3, 3), "K")
    with pytest.raises(ShapeError, match="numeric array"):
        check_shape([["a", "b"]], (1, 2), "K")


def test_detectors_refuse_an_unknown_option_with_the_typed_error():
    with pytest.raises(OptionError, match="refine must be one of"):
        OpenCVDetector(refine="subpixel")


def test_estimate_pose_refuses_a_malformed_camera_matrix_before_opencv_sees_it():
    board = BoardSpec()
    ids = np.arange(8)
    corners = board.object_points()[ids, :2] * 2000 + 100
    detection = Detection(ids=ids, corners=corners.astype(np.float32), scores=np.ones(8, np.float32))
    K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    assert estimate_pose(detection, K, None, board) is not None
    with pytest.raises(ShapeError, match=r"K must have shape \(3, 3\), got \(4,\)"):
        estimate_pose(detection, [800, 800, 320, 240], None, board)
    with pytest.raises(ShapeError, match="K holds NaN"):
        estimate_pose(detection, K * np.nan, None, board)
