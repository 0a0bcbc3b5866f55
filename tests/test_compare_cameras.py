import numpy as np

from deepcharuco import Camera, write_camera
from evaluate.compare_cameras import comparison_rows, main, ray_disagreement, stated_rms


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
