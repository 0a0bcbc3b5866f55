import cv2
import numpy as np
import pytest

from deepcharuco import BoardSpec, Camera, CameraFileError, OpenCVDetector, read_camera, write_camera
from deepcharuco.boards.synthetic import look_at_pose, render_board_view


def test_round_trip(tmp_path):
    camera = Camera(np.array([[412.3, 0.2, 318.1], [0, 410.9, 242.7], [0, 0, 1]]),
                    np.array([0.11, -0.23, 0.001, -0.002, 0.05]), (640, 480))
    path = write_camera(tmp_path / "cam.yaml", camera)
    assert path.read_text().startswith(("%YAML:1.0", "%YAML 1.2"))  # OpenCV 4's header, OpenCV 5's
    loaded = read_camera(path)
    np.testing.assert_allclose(loaded.K, camera.K)
    np.testing.assert_allclose(loaded.dist, camera.dist)
    assert loaded.image_size == (640, 480)


def test_reads_what_opencv_calibration_writes(tmp_path):
    # The layout of OpenCV's calibration sample: 1x5 distortion row, extra nodes ignored.
    storage = cv2.FileStorage(str(tmp_path / "calib.yml"), cv2.FILE_STORAGE_WRITE)
    storage.write("calibration_time", "today")
    storage.write("image_width", 320)
    storage.write("image_height", 240)
    storage.write("camera_matrix", np.array([[280.0, 0, 160], [0, 281.0, 120], [0, 0, 1]]))
    storage.write("distortion_coefficients", np.array([[0.1, 0.01, 0, 0, 0]]))
    storage.write("avg_reprojection_error", 0.12)
    storage.release()
    camera = read_camera(tmp_path / "calib.yml")
    assert camera.dist.shape == (5,) and camera.K[1, 1] == 281.0


def test_scaling_follows_resized_images():
    """Corners found in a resized image match the projection through the scaled K."""
    board = BoardSpec()
    big = Camera.from_fov(640, 480, 60.0)
    rvec, tvec = look_at_pose(board, 0.35, 20, -15, 10)
    image = render_board_view(board, big.K, rvec, tvec, big.image_size)
    small = cv2.resize(image, (320, 240), interpolation=cv2.INTER_AREA)
    scaled = big.scaled(320, 240)
    detection = OpenCVDetector(board).detect(small)
    projected, _ = cv2.projectPoints(board.corner_points()[detection.ids], rvec, tvec, scaled.K, None)
    errors = np.linalg.norm(projected.reshape(-1, 2) - detection.corners, axis=1)
    assert len(detection) == 16 and np.median(errors) < 0.1
    # Pixel-centre convention: u' = (u + 0.5) * s - 0.5.
    assert scaled.K[0, 2] == pytest.approx((big.K[0, 2] + 0.5) * 0.5 - 0.5)
    np.testing.assert_allclose(scaled.scaled(640, 480).K, big.K)
    # For frames of another size: the same camera, scaled, or refused when the frames are cropped.
    assert big.for_image_size(640, 480) is big
    np.testing.assert_allclose(big.for_image_size(320, 240).K, scaled.K)
    with pytest.raises(CameraFileError, match=r"different aspect ratio \(cropped\?\)"):
        big.for_image_size(640, 360)
    with pytest.raises(CameraFileError, match=r"different aspect ratio \(rotated \(portrait against landscape"):
        big.for_image_size(480, 640)


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(CameraFileError, match="does not exist: calibrate the camera first"):
        read_camera(tmp_path / "nope.yaml")
    (tmp_path / "plain.yaml").write_text("camera_matrix: [1, 2, 3]\n")
    with pytest.raises(CameraFileError, match="not an OpenCV FileStorage file"):
        read_camera(tmp_path / "plain.yaml")
    storage = cv2.FileStorage(str(tmp_path / "nok.yaml"), cv2.FILE_STORAGE_WRITE)
    storage.write("image_width", 320)
    storage.release()
    with pytest.raises(CameraFileError, match="has no camera_matrix"):
        read_camera(tmp_path / "nok.yaml")
    storage = cv2.FileStorage(str(tmp_path / "nosize.yaml"), cv2.FILE_STORAGE_WRITE)
    storage.write("camera_matrix", np.eye(3))
    storage.release()
    with pytest.raises(CameraFileError, match="lacks image_width"):
        read_camera(tmp_path / "nosize.yaml")


def test_invalid_intrinsics():
    with pytest.raises(CameraFileError, match="3x3"):
        Camera(np.eye(2), None, (320, 240))
    with pytest.raises(CameraFileError, match="not a pinhole matrix"):
        Camera(np.diag([-1.0, 1.0, 1.0]), None, (320, 240))
    with pytest.raises(CameraFileError, match="distortion_coefficients"):
        Camera(np.eye(3), np.zeros(3), (320, 240))
    with pytest.raises(CameraFileError, match="image size"):
        Camera(np.eye(3), None, (0, 240))
