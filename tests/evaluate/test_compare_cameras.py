import numpy as np

from deepcharuco import Camera, write_camera
from evaluate.calibration.compare_cameras import comparison_rows, main, ray_disagreement, stated_rms


def test_identical_cameras_agree_and_a_shifted_one_does_not(tmp_path):
    K = np.array([[900.0, 0.0, 640.0], [0.0, 900.0, 360.0], [0.0, 0.0, 1.0]])
    camera = Camera(K=K, dist=np.array([-0.3, 0.09, 0.0, 0.0, 0.0]), image_size=(1280, 720))
    assert max(ray_disagreement(camera, camera)) < 1e-9
    # The same camera calibrated at half the resolution is the same camera.
    assert max(ray_disagreement(camera, camera.scaled(640, 360))) < 1e-6
    shifted = Camera(K=K + np.array([[0, 0, 5.0], [0, 0, 0], [0, 0, 0]]), dist=camera.dist, image_size=(1280, 720))
    corners, centre = ray_disagreement(camera, shifted)
    assert abs(centre - 5.0) < 1e-6 and corners > 4.0


def test_rows_and_stated_rms(tmp_path, capsys):
    camera = Camera.from_fov(1280, 720, 70.0)
    write_camera(tmp_path / "a.yaml", camera)
    (tmp_path / "b.yaml").write_text((tmp_path / "a.yaml").read_text() + 'note: "tool X (reproj error 0.541)"\n')
    assert stated_rms(tmp_path / "a.yaml") is None and stated_rms(tmp_path / "b.yaml") == 0.541
    rows = comparison_rows([tmp_path / "a.yaml", tmp_path / "b.yaml"], ["first", "second"])
    assert rows[2][0] == "second" and rows[2][10] == "0.541" and rows[2][-2:] == ["0.0", "0.0"]
    assert main([str(tmp_path / "a.yaml"), str(tmp_path / "missing.yaml")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_a_fisheye_file_is_compared_through_its_own_model(tmp_path):
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    fisheye = Camera(K=K, dist=np.array([0.05, -0.01, 0.002, 0.0]), image_size=(640, 480), model="fisheye")
    assert max(ray_disagreement(fisheye, fisheye)) < 1e-6
    # Read as k1 k2 p1 p2 of the standard model, the same numbers are another camera.
    misread = Camera(K=K, dist=fisheye.dist, image_size=(640, 480))
    assert ray_disagreement(fisheye, misread)[0] > 5.0
    write_camera(tmp_path / "f.yaml", fisheye)
    rows = comparison_rows([tmp_path / "f.yaml", tmp_path / "f.yaml"], ["a", "b"])
    assert rows[1][0] == "a (fisheye)" and rows[2][-2:] == ["0.0", "0.0"]
