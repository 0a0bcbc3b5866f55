"""calibrate --export (deepcharuco.calibration.exports, .stereo, cli.calibration_exports): every file read back by its
format's reference reader (pycolmap for COLMAP) or checked against its documented layout (Kalibr's camchain, ROS's
camera_info), then the board projected with the numbers read back onto the pixels the OpenCV camera file puts it at."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from deepcharuco import Camera, read_camera, write_camera
from deepcharuco.calibration.exports import ExportRig, check_cameras, export_files, parse_exports
from deepcharuco.cli.calibrate import main
from deepcharuco.core.errors import ExportError
from evaluate.calibration.rig_views import RIG_BOARD, board_poses, drawn_rig, rig_cameras

yaml = pytest.importorskip("yaml")
pycolmap = pytest.importorskip("pycolmap")

SIZE = (640, 480)
# What each reprojection must meet: the target was 1e-6 px; the files' decimal text round-trips every float, and the
# exports measure <= 2e-13 px from the camera files' own projections.
TOLERANCE_PX = 1e-9


def truth(model: str, cameras: int = 3, seed: int = 5) -> tuple[ExportRig, np.ndarray]:
    """A rig of ``cameras`` drawn cameras (two: a stereo pair) of ``model`` ("pinhole": k1 k2 p1 p2; "pinhole_k3"; "rational"; "fisheye")
    and (K, N, 3) board corners at K poses in the rig's frame (camera 0's)."""
    rng = np.random.default_rng(seed)
    intrinsics, rotations, translations, target = rig_cameras(rng, cameras, SIZE)
    out = []
    for camera in intrinsics:
        k1, k2 = camera.dist[:2]
        dist = {"pinhole": [k1, k2, 1e-3, -6e-4, 0.0], "pinhole_k3": [k1, k2, 1e-3, -6e-4, 0.02],
                "rational": [k1, k2, 1e-3, -6e-4, 0.02, 0.05, -0.01, 0.004],
                "fisheye": [0.3 * k1, 0.02, -0.004, 0.001]}[model]
        out.append(Camera(camera.K, np.array(dist), SIZE, "fisheye" if model == "fisheye" else "pinhole"))
    if cameras == 2:  # a stereo pair: the second camera 12 cm to the right of the first, turned 2.5 degrees in
        rotations[1] = cv2.Rodrigues(np.array([0.01, -0.04, 0.005]))[0]
        translations[1] = -rotations[1] @ np.array([0.12, 0.004, -0.003])
    board_r, board_t = board_poses(rng, RIG_BOARD, target, 4)
    points = np.stack([RIG_BOARD.object_points() @ R.T + t for R, t in zip(board_r, board_t)])
    overlaps = [[d for d in range(cameras) if d != c] for c in range(cameras)]
    return ExportRig(out, [f"cam{c}" for c in range(cameras)], rotations, translations, overlaps), points


def in_camera(rig: ExportRig, c: int, points: np.ndarray) -> np.ndarray:
    """(N, 3) the rig-frame points in camera c's frame."""
    return points @ rig.rotations[c].T + rig.translations[c]


def opencv_pixels(camera: Camera, points_cam: np.ndarray) -> np.ndarray:
    """Where the camera file's model (`Camera.project`: cv2.projectPoints or cv2.fisheye.projectPoints) puts them."""
    return camera.project(points_cam, np.zeros(3), np.zeros(3))


def project_with(K: np.ndarray, dist: np.ndarray, fisheye: bool, points_cam: np.ndarray) -> np.ndarray:
    points = np.asarray(points_cam, np.float64).reshape(-1, 1, 3)
    if fisheye:
        return cv2.fisheye.projectPoints(points, np.zeros(3), np.zeros(3), K, dist)[0].reshape(-1, 2)
    return cv2.projectPoints(points, np.zeros(3), np.zeros(3), K, dist)[0].reshape(-1, 2)


def worst(pixels_a: np.ndarray, pixels_b: np.ndarray) -> float:
    return float(np.abs(np.asarray(pixels_a) - np.asarray(pixels_b)).max())


def read_kalibr(path) -> list[tuple[dict, np.ndarray]]:
    """Each camera's camchain entry, checked against Kalibr's documented camchain layout, with the 4 x 4 transform
    from camera 0's frame to its own composed along the T_cn_cnm1 chain."""
    chain = yaml.safe_load(path.read_text())
    assert list(chain) == [f"cam{c}" for c in range(len(chain))]
    out, T = [], np.eye(4)
    for c in range(len(chain)):
        entry = chain[f"cam{c}"]
        keys = {"camera_model", "intrinsics", "distortion_model", "distortion_coeffs", "resolution", "rostopic"}
        keys |= ({"T_cn_cnm1"} if c else set()) | ({"cam_overlaps"} if len(chain) > 1 else set())
        assert set(entry) == keys, entry.keys()
        assert entry["camera_model"] == "pinhole" and entry["distortion_model"] in ("radtan", "equidistant")
        assert len(entry["intrinsics"]) == 4 and len(entry["distortion_coeffs"]) == 4
        assert all(isinstance(v, float) for v in entry["intrinsics"] + entry["distortion_coeffs"])
        assert entry["rostopic"].startswith("/") and all(isinstance(v, int) for v in entry["resolution"])
        # What Kalibr's own reader (kalibr_common.ConfigReader) checks besides: a principal point >= 0, overlaps that
        # name cameras of the chain.
        assert min(entry["intrinsics"][2:]) >= 0 and all(0 <= o < len(chain) for o in entry.get("cam_overlaps", []))
        if c:
            step = np.array(entry["T_cn_cnm1"], np.float64)
            assert step.shape == (4, 4) and np.array_equal(step[3], [0, 0, 0, 1])
            T = step @ T
        out.append((entry, T.copy()))
    return out


@pytest.mark.parametrize("model", ["pinhole", "fisheye"])
def test_kalibr_camchain_projects_the_board_through_its_chain_onto_the_camera_files_pixels(tmp_path, model):
    rig, points = truth(model)
    files = export_files(["kalibr"], rig, tmp_path)
    assert list(files) == [tmp_path / "kalibr" / "camchain.yaml"]
    path = tmp_path / "kalibr" / "camchain.yaml"
    path.parent.mkdir()
    path.write_text(files[path])
    in_cam0 = in_camera(rig, 0, points.reshape(-1, 3))
    for c, (entry, T) in enumerate(read_kalibr(path)):
        fu, fv, pu, pv = entry["intrinsics"]
        K = np.array([[fu, 0, pu], [0, fv, pv], [0, 0, 1.0]])
        assert entry["distortion_model"] == ("equidistant" if model == "fisheye" else "radtan")
        assert entry["resolution"] == list(SIZE) and entry["rostopic"] == f"/cam{c}/image_raw"
        chained = in_cam0 @ T[:3, :3].T + T[:3, 3]  # camera 0's frame carried into camera c's by T_cn_cnm1
        exported = project_with(K, np.array(entry["distortion_coeffs"]), model == "fisheye", chained)
        assert worst(exported, opencv_pixels(rig.cameras[c], in_camera(rig, c, points.reshape(-1, 3)))) < TOLERANCE_PX


def read_colmap_cameras(folder):
    """cameras.txt read by COLMAP's own reader (pycolmap), as a sparse model with no images."""
    model = folder / "model"
    model.mkdir()
    (model / "cameras.txt").write_text((folder / "cameras.txt").read_text())
    for name in ("images.txt", "points3D.txt"):
        (model / name).write_text("")
    reconstruction = pycolmap.Reconstruction()
    reconstruction.read_text(str(model))
    return reconstruction.cameras


@pytest.mark.parametrize("model, colmap", [("pinhole", "OPENCV"), ("pinhole_k3", "FULL_OPENCV"),
                                           ("rational", "FULL_OPENCV"), ("fisheye", "OPENCV_FISHEYE")])
def test_colmap_cameras_and_rig_config_read_by_pycolmap_project_the_board_onto_the_camera_files_pixels(tmp_path, model,
                                                                                                      colmap):
    rig, points = truth(model)
    for path, text in export_files(["colmap"], rig, tmp_path).items():
        path.parent.mkdir(exist_ok=True)
        path.write_text(text)
    folder = tmp_path / "colmap"
    assert (folder / "cameras.txt").read_text().startswith("# Camera list with one line of data per camera:\n")
    cameras = read_colmap_cameras(folder)
    configs = pycolmap.read_rig_config(str(folder / "rig_config.json"))
    assert len(configs) == 1 and len(configs[0].cameras) == len(rig.cameras)
    flat = points.reshape(-1, 3)
    for c, camera in enumerate(rig.cameras):
        expected = opencv_pixels(camera, in_camera(rig, c, flat))
        read = cameras[c + 1]
        assert read.model_name == colmap and (read.width, read.height) == SIZE
        # COLMAP's pixels put the top-left pixel's centre at (0.5, 0.5): OpenCV's are 0.5 less.
        assert worst(read.img_from_cam(in_camera(rig, c, flat)) - 0.5, expected) < TOLERANCE_PX
        entry = configs[0].cameras[c]
        assert entry.image_prefix == f"cam{c}/" and entry.ref_sensor == (c == 0)
        from_rig = in_camera(rig, 0, flat) if c == 0 else entry.cam_from_rig * in_camera(rig, 0, flat)
        assert worst(entry.camera.img_from_cam(from_rig) - 0.5, expected) < TOLERANCE_PX


def read_ros(path) -> dict:
    """A camera_info YAML checked against ROS's layout (camera_calibration_parsers), its matrices as arrays."""
    info = yaml.safe_load(path.read_text())
    assert set(info) == {"image_width", "image_height", "camera_name", "camera_matrix", "distortion_model",
                         "distortion_coefficients", "rectification_matrix", "projection_matrix"}
    shapes = {"camera_matrix": (3, 3), "rectification_matrix": (3, 3), "projection_matrix": (3, 4)}
    for key in ("camera_matrix", "distortion_coefficients", "rectification_matrix", "projection_matrix"):
        node = info[key]
        assert set(node) == {"rows", "cols", "data"} and len(node["data"]) == node["rows"] * node["cols"]
        assert shapes.get(key, (1, node["cols"])) == (node["rows"], node["cols"])
        info[key] = np.array(node["data"], np.float64).reshape(node["rows"], node["cols"])
    return info


@pytest.mark.parametrize("model, ros", [("pinhole", "plumb_bob"), ("rational", "rational_polynomial"),
                                        ("fisheye", "equidistant")])
def test_ros_camera_info_of_a_rig_is_a_mono_camera_each_projecting_the_board_onto_the_camera_files_pixels(tmp_path,
                                                                                                         model, ros):
    rig, points = truth(model)
    for path, text in export_files(["ros"], rig, tmp_path).items():
        path.parent.mkdir(exist_ok=True)
        path.write_text(text)
    for c, camera in enumerate(rig.cameras):
        info = read_ros(tmp_path / "ros" / f"cam{c}.yaml")
        assert (info["image_width"], info["image_height"]) == SIZE and info["camera_name"] == f"cam{c}"
        assert info["distortion_model"] == ros
        assert info["distortion_coefficients"].size == {"plumb_bob": 5, "rational_polynomial": 8, "equidistant": 4}[ros]
        K = info["camera_matrix"]
        assert np.array_equal(info["rectification_matrix"], np.eye(3))  # three cameras: each a mono camera
        assert np.array_equal(info["projection_matrix"], np.column_stack([K, np.zeros(3)]))
        flat = in_camera(rig, c, points.reshape(-1, 3))
        exported = project_with(K, info["distortion_coefficients"].ravel(), ros == "equidistant", flat)
        assert worst(exported, opencv_pixels(camera, flat)) < TOLERANCE_PX
        # ... and it is a camera file for `detect --camera` (read_camera): the same camera, model and all
        read = read_camera(tmp_path / "ros" / f"cam{c}.yaml")
        assert read.model == camera.model and read.image_size == camera.image_size
        assert np.allclose(read.K, camera.K, rtol=1e-12) and np.allclose(read.dist, camera.dist, rtol=1e-12)


def bilinear(image: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    x, y = pixels[:, 0], pixels[:, 1]
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    at = (lambda dy, dx: image[y0 + dy, x0 + dx].astype(np.float64))  # noqa: E731
    return (at(0, 0) * (1 - fx) * (1 - fy) + at(0, 1) * fx * (1 - fy) + at(1, 0) * (1 - fx) * fy + at(1, 1) * fx * fy)


@pytest.mark.parametrize("model", ["pinhole", "fisheye"])
def test_a_pair_is_rectified_rows_agree_and_the_maps_lead_back_to_each_cameras_pixels(tmp_path, model):
    rig, points = truth(model, cameras=2)
    for path, data in export_files(["ros", "opencv"], rig, tmp_path, maps=True).items():
        path.parent.mkdir(exist_ok=True)
        path.write_bytes(data if isinstance(data, bytes) else data.encode())
    storage = cv2.FileStorage(str(tmp_path / "opencv" / "stereo.yaml"), cv2.FILE_STORAGE_READ)
    node = {key: storage.getNode(key).mat() for key in ("M1", "D1", "M2", "D2", "R", "T", "R1", "R2", "P1", "P2", "Q")}
    assert storage.getNode("cameras").string() == "cam0 cam1"
    storage.release()
    maps = np.load(tmp_path / "opencv" / "rectify_maps.npz")
    flat = points.reshape(-1, 3)
    rectified = []
    for c, camera in enumerate(rig.cameras):
        info = read_ros(tmp_path / "ros" / f"cam{c}.yaml")
        R, P = node[f"R{c + 1}"], node[f"P{c + 1}"]
        assert np.array_equal(info["rectification_matrix"], R) and np.array_equal(info["projection_matrix"], P)
        assert np.array_equal(node[f"M{c + 1}"], camera.K) and np.array_equal(node[f"D{c + 1}"].ravel(), camera.dist)
        # Rectified camera c sees its point R_c x_c through P_c's 3 x 3; P_c itself takes the point in the first
        # rectified camera's frame (R1 x_0), its 4th column the offset between the two (ROS's P).
        pixels = in_camera(rig, c, flat) @ R.T @ P[:, :3].T
        pixels = pixels[:, :2] / pixels[:, 2:]
        through_p = np.column_stack([in_camera(rig, 0, flat) @ node["R1"].T, np.ones(len(flat))]) @ P.T
        assert worst(through_p[:, :2] / through_p[:, 2:], pixels) < TOLERANCE_PX
        rectified.append(pixels)
        # The maps send each rectified pixel back to where the camera file's model sees the point.
        inside = ((pixels >= 0) & (pixels < np.array(SIZE) - 1)).all(1)  # alpha 0: the rectified image is cropped
        assert inside.sum() > 100
        back = np.column_stack([bilinear(maps[f"cam{c}_map_x"], pixels[inside]),
                                bilinear(maps[f"cam{c}_map_y"], pixels[inside])])
        assert worst(back, opencv_pixels(camera, in_camera(rig, c, flat[inside]))) < 2e-3
    assert worst(rectified[0][:, 1], rectified[1][:, 1]) < TOLERANCE_PX  # one row in both rectified images
    # Q takes (u, v, disparity) back to the point in the first rectified camera's frame.
    disparity = rectified[0][:, 0] - rectified[1][:, 0]
    homogeneous = np.column_stack([rectified[0], disparity, np.ones(len(disparity))]) @ node["Q"].T
    assert worst(homogeneous[:, :3] / homogeneous[:, 3:], in_camera(rig, 0, flat) @ node["R1"].T) < 1e-9
    R, T = rig.relative(0, 1)
    assert np.allclose(node["R"], R, atol=1e-15) and np.allclose(node["T"].ravel(), T, atol=1e-15)


def test_one_cameras_undistortion_and_its_maps(tmp_path):
    rig, points = truth("rational", cameras=1)
    rig = ExportRig.single(rig.cameras[0], "solo")
    files = export_files(["opencv"], rig, tmp_path, maps=True)
    assert sorted(p.name for p in files) == ["rectify_maps.npz", "undistort.yaml"]
    for path, data in files.items():
        path.parent.mkdir(exist_ok=True)
        path.write_bytes(data if isinstance(data, bytes) else data.encode())
    storage = cv2.FileStorage(str(tmp_path / "opencv" / "undistort.yaml"), cv2.FILE_STORAGE_READ)
    new_K = storage.getNode("new_camera_matrix").mat()
    storage.release()
    maps = np.load(tmp_path / "opencv" / "rectify_maps.npz")
    flat = points.reshape(-1, 3)
    undistorted = flat @ new_K.T
    undistorted = undistorted[:, :2] / undistorted[:, 2:]
    inside = ((undistorted >= 0) & (undistorted < np.array(SIZE) - 1)).all(1)
    assert inside.sum() > 50
    back = np.column_stack([bilinear(maps["solo_map_x"], undistorted[inside]),
                            bilinear(maps["solo_map_y"], undistorted[inside])])
    assert worst(back, opencv_pixels(rig.cameras[0], flat[inside])) < 2e-3


@pytest.mark.parametrize("formats, model, cameras, message", [
    (["kalibr"], "pinhole_k3", 3, "--export kalibr: cam0 has k3, which Kalibr's radtan model (k1 k2 p1 p2) has no term"),
    (["kalibr"], "rational", 3, "cam0 has k3..k6 (the rational model)"),
    (["opencv"], "pinhole", 3, ("--export opencv is a stereo pair's rectification (or one camera's undistortion); "
                                "this rig has 3 cameras")),
])
def test_a_camera_a_format_cannot_hold_is_refused(model, formats, cameras, message):
    rig, _ = truth(model, cameras)
    with pytest.raises(ExportError, match=message.replace("(", r"\(").replace(")", r"\)").replace(".", r"\.")):
        export_files(formats, rig, None)


def test_other_refusals_and_the_names():
    assert parse_exports(["ros,kalibr", "COLMAP", "ros"]) == ["kalibr", "ros", "colmap"]
    with pytest.raises(ExportError, match="--export bundler is not a format written here: give kalibr, ros, colmap"):
        parse_exports(["ros,bundler"])
    rig, _ = truth("pinhole", 2)
    small = Camera(rig.cameras[1].K, rig.cameras[1].dist, (320, 240))
    with pytest.raises(ExportError, match="cam0 is 640x480 and cam1 320x240: OpenCV rectifies a pair of one image size"):
        check_cameras(["opencv"], [rig.cameras[0], small], rig.names)
    thin_prism = Camera(rig.cameras[0].K, np.r_[rig.cameras[0].dist, np.zeros(3), 1e-3, 0, 0, 0], SIZE)
    for fmt in ("ros", "colmap"):
        with pytest.raises(ExportError, match=f"--export {fmt}: a has 12 distortion coefficients"):
            check_cameras([fmt], [thin_prism], ["a"])


# ----------------------------------------------------------------------------------------------- the command
@pytest.fixture(scope="module")
def drawn(tmp_path_factory):
    """Two cameras' folders of drawn frames (good light), a board file, and the true cameras' files (k1 k2: radtan)."""
    truth_rig = drawn_rig(RIG_BOARD, seed=11, cameras=2, instants=16)
    root = tmp_path_factory.mktemp("pair")
    cameras = [write_camera(root / f"true{c}.yaml", camera) for c, camera in enumerate(truth_rig.cameras)]
    return truth_rig.save_frames(root), RIG_BOARD.save(root / "board.yaml"), cameras


def camera_file(path) -> tuple[Camera, np.ndarray, np.ndarray]:
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    R, t = storage.getNode("rotation_matrix").mat(), storage.getNode("translation_vector").mat().ravel()
    storage.release()
    return read_camera(path), R, t


def test_the_command_exports_a_pair_in_every_format_matching_its_camera_files(tmp_path, drawn, capsys):
    folders, board, true_files = drawn
    out = tmp_path / "rig"
    # The intrinsics held at the true cameras' (the quicker solve: the exports are what is tested here).
    assert main([*map(str, folders), "--board", str(board), "--detector", "opencv", "--out", str(out), "--quiet",
                 "--no-report", "--camera", str(true_files[0]), "--camera", str(true_files[1]), "--export",
                 "kalibr,ros", "--export", "colmap", "--export", "opencv", "--rectify-maps"]) == 0
    files = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())
    assert files == sorted(["cam0.yaml", "cam1.yaml", "colmap/cameras.txt", "colmap/rig_config.json", "kalibr/camchain.yaml",
                     "opencv/rectify_maps.npz", "opencv/stereo.yaml", "ros/cam0.yaml", "ros/cam1.yaml", "rig.toml"])
    written = [camera_file(out / f"cam{c}.yaml") for c in range(2)]
    rig = ExportRig([w[0] for w in written], ["cam0", "cam1"], np.stack([w[1] for w in written]),
                    np.stack([w[2] for w in written]))
    assert all(camera.dist[4] == 0 for camera in rig.cameras)  # radtan holds them exactly
    _, points = truth("pinhole", 2, seed=11)
    flat = points.reshape(-1, 3)
    chain = read_kalibr(out / "kalibr" / "camchain.yaml")
    cameras = read_colmap_cameras(out / "colmap")
    config = pycolmap.read_rig_config(str(out / "colmap" / "rig_config.json"))[0]
    for c, camera in enumerate(rig.cameras):
        expected = opencv_pixels(camera, in_camera(rig, c, flat))
        entry, T = chain[c]
        fu, fv, pu, pv = entry["intrinsics"]
        K = np.array([[fu, 0, pu], [0, fv, pv], [0, 0, 1.0]])
        chained = in_camera(rig, 0, flat) @ T[:3, :3].T + T[:3, 3]
        assert worst(project_with(K, np.array(entry["distortion_coeffs"]), False, chained), expected) < TOLERANCE_PX
        assert entry["cam_overlaps"] == [1 - c]
        assert worst(cameras[c + 1].img_from_cam(in_camera(rig, c, flat)) - 0.5, expected) < TOLERANCE_PX
        from_rig = in_camera(rig, 0, flat) if c == 0 else config.cameras[c].cam_from_rig * in_camera(rig, 0, flat)
        assert worst(config.cameras[c].camera.img_from_cam(from_rig) - 0.5, expected) < TOLERANCE_PX
        info = read_ros(out / "ros" / f"cam{c}.yaml")
        ros = project_with(info["camera_matrix"], info["distortion_coefficients"].ravel(), False, in_camera(rig, c, flat))
        assert info["distortion_model"] == "plumb_bob" and worst(ros, expected) < TOLERANCE_PX
    assert np.load(out / "opencv" / "rectify_maps.npz")["cam1_map_x"].shape == (SIZE[1], SIZE[0])
    # One camera of it, calibrated with the fisheye model: Kalibr's equidistant, ROS's, COLMAP's OPENCV_FISHEYE.
    single = tmp_path / "single" / "left.yaml"
    assert main([str(folders[0]), "--board", str(board), "--detector", "opencv", "--out", str(single), "--quiet",
                 "--no-report", "--model", "fisheye", "--export", "kalibr,ros,colmap,opencv"]) == 0
    camera = read_camera(single)
    exports = single.parent / "left_exports"
    assert sorted(str(p.relative_to(exports)) for p in exports.rglob("*") if p.is_file()) == [
        "colmap/cameras.txt", "kalibr/camchain.yaml", "opencv/undistort.yaml", "ros/left.yaml"]
    expected = opencv_pixels(camera, flat)
    (entry, _), = read_kalibr(exports / "kalibr" / "camchain.yaml")
    fu, fv, pu, pv = entry["intrinsics"]
    K = np.array([[fu, 0, pu], [0, fv, pv], [0, 0, 1.0]])
    assert entry["distortion_model"] == "equidistant"
    assert worst(project_with(K, np.array(entry["distortion_coeffs"]), True, flat), expected) < TOLERANCE_PX
    colmap = read_colmap_cameras(exports / "colmap")[1]
    assert colmap.model_name == "OPENCV_FISHEYE" and worst(colmap.img_from_cam(flat) - 0.5, expected) < TOLERANCE_PX
    info = read_ros(exports / "ros" / "left.yaml")
    assert info["distortion_model"] == "equidistant"
    assert worst(project_with(info["camera_matrix"], info["distortion_coefficients"].ravel(), True, flat),
                 expected) < TOLERANCE_PX


@pytest.mark.parametrize("extra, sources, message", [
    (["--export", "ros,bundler"], 2, "--export bundler is not a format written here"),
    (["--export", "kalibr"], 2, "--export kalibr: Kalibr's radtan model has k1 k2 p1 p2 and no k3: add --fix-k3"),
    (["--export", "kalibr", "--model", "rational"], 2, "--export kalibr: a rational model (k4 k5 k6) cannot be written"),
    (["--export", "opencv"], 3, ("--export opencv is a stereo pair's rectification (or one camera's undistortion); 3 "
                                "sources are not a pair")),
    (["--export", "ros", "--rectify-maps"], 2, "--rectify-maps writes the maps of --export opencv's rectification"),
    (["--export", "kalibr", "--model", "rational"], 1, "--export kalibr: a rational model (k4 k5 k6)"),
    (["--export", "kalibr", "--camera", "K3.yaml", "--camera", "K3.yaml"], 2, "--export kalibr: K3.yaml has k3, which Kalibr's radtan"),
])
def test_export_options_are_refused_before_any_work(tmp_path, drawn, capsys, monkeypatch, extra, sources, message):
    folders, board, _ = drawn
    monkeypatch.chdir(tmp_path)
    if "K3.yaml" in extra:  # a camera held at a file with k3, which radtan cannot hold
        write_camera(tmp_path / "K3.yaml", Camera(np.diag([500.0, 500, 1]), np.array([-0.2, 0.05, 0, 0, 0.01]), SIZE))
    given = [str(folders[0]), str(folders[1]), str(folders[0])][:sources]
    with pytest.raises(SystemExit) as stop:
        main([*given, "--board", str(board), "--detector", "opencv", "--out", "out", *extra])
    assert stop.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_an_export_file_in_the_way_is_refused_before_the_solve(tmp_path, drawn, capsys, monkeypatch):
    folders, board, _ = drawn
    (tmp_path / "rig" / "kalibr").mkdir(parents=True)
    (tmp_path / "rig" / "kalibr" / "camchain.yaml").write_text("cam0: {camera_model: pinhole}  # the user's own\n")

    def no_solve(*args, **kwargs):
        raise AssertionError("solved before the refusal")

    monkeypatch.setattr("deepcharuco.cli.calibrate_rig.solve_rig", no_solve)
    assert main([*map(str, folders), "--board", str(board), "--detector", "opencv", "--out", str(tmp_path / "rig"),
                 "--quiet", "--fix-k3", "--export", "kalibr"]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "kalibr/camchain.yaml exists and is not a Kalibr camchain it wrote" in error[0]
    assert "the user's own" in (tmp_path / "rig" / "kalibr" / "camchain.yaml").read_text()


def test_yaml_numbers_read_back_as_the_same_floats():
    """YAML 1.1 (PyYAML, Kalibr's and ROS's Python readers) reads 1e-05 as a string: every number is written so that
    it reads back as the float it was."""
    camera = Camera(np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]), np.array([-0.2, 1e-05, 3e-20, -1e-7, 0]),
                    SIZE)
    rig = ExportRig.single(camera, "tiny")
    files = export_files(["kalibr", "ros"], rig, Path("x"))
    kalibr, ros = (yaml.safe_load(text) for text in files.values())
    assert kalibr["cam0"]["distortion_coeffs"] == [-0.2, 1e-05, 3e-20, -1e-7]
    assert ros["distortion_coefficients"]["data"] == [-0.2, 1e-05, 3e-20, -1e-7, 0.0]
