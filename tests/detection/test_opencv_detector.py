
import cv2
import numpy as np
import pytest

from conftest import ROOT, VIEW_POSES, make_view, rotation_error_deg
from deepcharuco import BoardSpec, Detection, ImageError, OpenCVDetector, match_corners
from deepcharuco.detection.opencv_detector import charuco_detector_bias


@pytest.mark.parametrize("refine", ["subpix", "none"])
def test_recovers_corners_and_pose_on_clean_views(default_views, camera, refine):
    detector = OpenCVDetector(refine=refine)
    corner_errors = []
    for image, rvec, tvec, truth in default_views:
        detection = detector.detect(image)
        assert isinstance(detection, Detection)
        assert detection.ids.tolist() == list(range(16))
        assert detection.corners.dtype == np.float32 and detection.scores.dtype == np.float32
        np.testing.assert_array_equal(detection.scores, 1.0)
        match = match_corners(detection, truth)
        assert match.accuracy == 1.0
        corner_errors.append(match.errors)
        pose = detector.estimate_pose(detection, camera.K, camera.dist)
        assert pose is not None
        assert pose.reprojection_error < 0.3
        assert rotation_error_deg(pose.rvec, rvec) < 1.0
        assert np.linalg.norm(pose.tvec - tvec) < 0.01 * np.linalg.norm(tvec)
    assert np.median(np.concatenate(corner_errors)) < 0.1


def test_opencv_half_pixel_bias_is_measured_and_removed():
    bias = charuco_detector_bias()
    assert bias.shape == (2,)
    assert set(bias.tolist()) <= {0.0, 0.5}


def test_non_default_board_through_the_same_code(camera):
    board = BoardSpec(7, 5, 0.03, 0.022, "DICT_6X6_250")
    detector = OpenCVDetector(board)
    for pose_args in VIEW_POSES[:3]:
        image, rvec, tvec, truth = make_view(board, camera, **{**pose_args, "distance": 0.38})
        detection = detector.detect(image)
        # every corner with OpenCV 4; OpenCV 5's detector leaves 2 of one view's out
        assert len(detection) >= (24 if int(cv2.__version__.split(".")[0]) < 5 else 22)
        match = match_corners(detection, truth)
        assert match.num_correct == len(detection)
        pose = detector.estimate_pose(detection, camera.K, camera.dist)
        assert pose.reprojection_error < 0.3
        assert rotation_error_deg(pose.rvec, rvec) < 1.0
    # The paper's detector does not see corners on this other board.
    assert len(OpenCVDetector().detect(image)) == 0


def test_empty_scene_gives_empty_detection():
    detection = OpenCVDetector().detect(np.full((240, 320), 128, np.uint8))
    assert len(detection) == 0 and detection.corners.shape == (0, 2)


def test_colour_input_is_converted(default_views):
    image = default_views[1][0]
    bgr = np.dstack([image, image, image])
    a, b = OpenCVDetector().detect(image), OpenCVDetector().detect(bgr)
    np.testing.assert_array_equal(a.ids, b.ids)
    np.testing.assert_allclose(a.corners, b.corners, atol=1e-4)


@pytest.mark.parametrize(
    "image, message",
    [
        (np.zeros((240, 320), np.float32), "expected a uint8 image, got dtype float32"),
        (np.zeros((240, 320), np.uint16), "expected a uint8 image, got dtype uint16"),
        (np.zeros((0, 0), np.uint8), "the image is empty"),
        (np.zeros((240, 320, 2), np.uint8), r"got shape \(240, 320, 2\)"),
        (np.zeros((2, 240, 320, 3), np.uint8), "got shape"),
        ([[0, 1], [2, 3]], "expected a numpy array image, got list"),
    ],
)
def test_bad_images_are_refused_clearly(image, message):
    with pytest.raises(ImageError, match=message):
        OpenCVDetector().detect(image)


def test_bad_arguments():
    with pytest.raises(ValueError, match="refine must be one of"):
        OpenCVDetector(refine="refinenet")
    with pytest.raises(ValueError, match="max_window"):
        OpenCVDetector(max_window=0)


def test_deep_detector_without_weights_explains_itself(monkeypatch, tmp_path):
    from deepcharuco import DeepCharucoError, Detector
    from deepcharuco.detection import deep_detector

    monkeypatch.setattr(deep_detector, "DEFAULT_WEIGHTS", tmp_path / "detector.pt")
    with pytest.raises(DeepCharucoError, match="no shipped weights"):
        Detector()


def test_shipped_weights_find_the_bundled_example():
    """The shipped bundle loads by default, for the paper's board, and agrees with OpenCV on a clean image: 15 of its
    16 corners found, all within 0.14 px of OpenCV's, median 0.06 px (2026-11-27), asserted within ~2x."""
    import cv2

    from deepcharuco import Detector

    detector = Detector()
    assert detector.board == BoardSpec() and detector.refine == "refinenet" and 0 < detector.threshold < 1
    image = cv2.imread(str(ROOT / "deepcharuco/examples/board_320x240.png"), cv2.IMREAD_GRAYSCALE)
    found, reference = detector.detect(image), OpenCVDetector(BoardSpec()).detect(image)
    truth = dict(zip(reference.ids.tolist(), reference.corners))
    errors = np.array([np.linalg.norm(c - truth[i]) for i, c in zip(found.ids.tolist(), found.corners) if i in truth])
    assert len(reference.ids) == 16 and len(found) == len(errors) >= 15, (found.ids, errors)  # no ID OpenCV lacks
    assert errors.max() < 0.3 and np.median(errors) < 0.12, errors


@pytest.mark.parametrize("mirrored", [False, True])
def test_detect_board_is_opencvs_call_in_shape_and_type(camera, mirrored):
    """detectBoard returns what cv2.aruco.CharucoDetector.detectBoard does, so a script written for it switches in
    one line; its corners are `detect`'s, and the markers lie on the board in the image (a mirrored board too)."""
    from deepcharuco import Detector

    board = BoardSpec(mirrored=mirrored)
    image = make_view(BoardSpec(), camera, **VIEW_POSES[0])[0]
    image = image[:, ::-1].copy() if mirrored else image
    theirs = cv2.aruco.CharucoDetector(BoardSpec().cv_board()).detectBoard(image[:, ::-1] if mirrored else image)
    for detector in (OpenCVDetector(board), Detector(board=board)):
        corners, ids, marker_corners, marker_ids = detector.detectBoard(image)
        found = detector.detect(image)
        n = len(found)
        assert n >= 12 and corners.shape == (n, 1, 2) and corners.dtype == np.float32
        assert ids.shape == (n, 1) and ids.dtype == np.int32
        assert np.array_equal(ids.ravel(), found.ids) and np.array_equal(corners.reshape(-1, 2), found.corners)
        assert isinstance(marker_corners, tuple)
        # Usable as OpenCV's output: matchImagePoints pairs them with the board's points.
        objects, pixels = board.cv_board().matchImagePoints(corners, ids)
        assert objects.size == 3 * n and pixels.size == 2 * n  # (n, 1, 3) from OpenCV 4, (n, 3) from OpenCV 5
    corners, ids, marker_corners, marker_ids = OpenCVDetector(board).detectBoard(image)
    assert len(marker_corners) == len(theirs[2]) == 12 and marker_ids.shape == np.shape(theirs[3])  # (12, 1); OpenCV 5: (12,)
    assert all(m.shape == (1, 4, 2) and m.dtype == np.float32 for m in marker_corners)
    # The markers are OpenCV's, in this image's pixels: a mirrored board's mapped back from the flipped view.
    expected = [m.reshape(4, 2).copy() for m in theirs[2]]
    if mirrored:
        for m in expected:
            m[:, 0] = image.shape[1] - 1 - m[:, 0]
    assert np.array_equal(marker_ids, theirs[3])
    assert max(np.abs(m.reshape(4, 2) - e).max() for m, e in zip(marker_corners, expected)) < 1e-4
    assert OpenCVDetector(board).detectBoard(np.full((240, 320), 128, np.uint8))[:2] == (None, None)
    assert Detector(board=board).detectBoard(np.full((240, 320), 128, np.uint8)) == (None, None, (), None)
