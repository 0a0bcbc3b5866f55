"""Backends (deepcharuco.networks.runtime): PyTorch and ONNX Runtime give the same corners; int8 only when accepted."""

import cv2
import numpy as np
import pytest
import torch
from threadpoolctl import ThreadpoolController, threadpool_limits

from conftest import VIEW_POSES, make_view
from deepcharuco import BoardSpec
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.detection.deep_detector import DEFAULT_WEIGHTS, Detector
from deepcharuco.networks.runtime import (INT8_KEY, int8_model, make_runner, onnxruntime_available, resolve_backend,
                                          weights_fingerprint)
from evaluate.paper.protocols import TestFrame
from train import quantize as quantize_module

EXAMPLE = cv2.imread(str(DEFAULT_WEIGHTS.parents[1] / "examples" / "board_320x240.png"), cv2.IMREAD_GRAYSCALE)
needs_onnxruntime = pytest.mark.skipif(not onnxruntime_available(), reason="ONNX Runtime not installed")


@needs_onnxruntime
@pytest.mark.parametrize("refine", ["refinenet", "subpix"])
def test_onnx_and_torch_find_the_same_corners(refine):
    image = cv2.resize(EXAMPLE, (640, 480), interpolation=cv2.INTER_LINEAR)  # two search levels
    torch_result = Detector(refine=refine, backend="torch").detect(image)
    onnx_detector = Detector(refine=refine, backend="onnx")
    onnx_result = onnx_detector.detect(image)
    assert onnx_detector.runner.name == "onnx" and "backend='onnx'" in repr(onnx_detector)
    assert len(torch_result) >= 15
    np.testing.assert_array_equal(onnx_result.ids, torch_result.ids)
    np.testing.assert_allclose(onnx_result.corners, torch_result.corners, atol=1e-3)


FAMILY_BOARDS = {"DICT_4X4": BoardSpec(5, 7, 0.03, 0.022, "DICT_4X4_50"),
                 "DICT_6X6": BoardSpec(7, 5, 0.03, 0.022, "DICT_6X6_250")}


@needs_onnxruntime
@pytest.mark.parametrize("family", list(FAMILY_BOARDS))
def test_family_models_run_in_onnx_runtime_as_in_pytorch(family, camera):
    """A family model (deepcharuco/weights/families) through ONNX Runtime and through PyTorch: the same point logits
    and RefineNet logits (measured 2026-11-27: at most 4e-5 and 1.3e-5 apart, on logits up to 63 and 32), and the
    same IDs, scores (1.4e-6 apart) and corners (equal) with RefineNet placing them (no pattern fit, which would
    hide the networks' differences)."""
    board = FAMILY_BOARDS[family]
    torch_detector = Detector(board=board, backend="torch", corner_fit=False)
    onnx_detector = Detector(board=board, backend="onnx", corner_fit=False)
    assert onnx_detector.runner.name == "onnx" and torch_detector.weights.parent.name == "families"
    assert torch_detector.weights.stem == family
    patches = []
    for pose in VIEW_POSES[:2]:
        image = make_view(board, camera, **pose)[0]
        batch = (image[None, None] / np.float32(255.0)).astype(np.float32)
        (points_t, _), (points_o, _) = torch_detector.runner.charuconet(batch), onnx_detector.runner.charuconet(batch)
        assert np.abs(points_t).max() > 10 and np.abs(points_o - points_t).max() < 1e-4
        a, b = torch_detector.detect(image), onnx_detector.detect(image)
        assert len(a) == board.num_corners and np.array_equal(a.ids, b.ids)
        assert np.abs(a.corners - b.corners).max() < 1e-4 and np.abs(a.scores - b.scores).max() < 5e-6
        patches.append(np.stack([cv2.getRectSubPix(image, (24, 24), tuple(map(float, c))) for c in a.corners[:8]]))
    patches = (np.concatenate(patches)[:, None] / np.float32(255.0)).astype(np.float32)
    heat_t, heat_o = torch_detector.runner.refinenet(patches), onnx_detector.runner.refinenet(patches)
    assert heat_t.shape == heat_o.shape == (len(patches), *heat_t.shape[1:]) and np.abs(heat_o - heat_t).max() < 4e-5


def test_auto_picks_by_device_and_installed_runtime():
    checkpoint = {}
    assert resolve_backend("auto", torch.device("cuda"), checkpoint) == "torch"
    expected = "onnx" if onnxruntime_available() else "torch"
    assert resolve_backend("auto", torch.device("cpu"), checkpoint) == expected
    with pytest.raises(ValueError, match="backend must be one of"):
        resolve_backend("tensorrt", torch.device("cpu"), checkpoint)
    with pytest.raises(DeepCharucoError, match="runs on the CPU"):
        resolve_backend("onnx", torch.device("cuda"), checkpoint)


@needs_onnxruntime
def test_int8_needs_an_int8_model(tmp_path):
    bundle = torch.load(DEFAULT_WEIGHTS, map_location="cpu", weights_only=True)
    bundle["charuconet"].pop(INT8_KEY, None)
    torch.save(bundle, tmp_path / "float.pt")
    assert Detector(weights=tmp_path / "float.pt").runner.name == "onnx"
    with pytest.raises(DeepCharucoError, match="python -m train.quantize"):
        Detector(weights=tmp_path / "float.pt", backend="onnx-int8")


def test_an_int8_model_of_other_weights_is_ignored():
    detector = Detector(backend="torch")
    fingerprint = weights_fingerprint(detector.charuconet)
    entry = {INT8_KEY: {"onnx": b"model", "weights_sha256": fingerprint}}
    assert int8_model(entry, fingerprint) == b"model"
    with pytest.warns(UserWarning, match="other float weights"):
        assert int8_model({INT8_KEY: {"onnx": b"model", "weights_sha256": "0" * 64}}, fingerprint) is None


@pytest.fixture(scope="module")
def validation_frames(camera=None):
    from deepcharuco.geometry.camera import Camera

    camera = Camera.from_fov(320, 240, hfov_deg=60.0)
    board = BoardSpec()
    frames = []
    for i, pose in enumerate([dict(distance=0.35, tilt_x_deg=20), dict(distance=0.4, tilt_y_deg=-25, roll_deg=10)]):
        image, rvec, tvec, corners = make_view(board, camera, **pose)
        frames.append(TestFrame(image, corners.astype(np.float32), np.ones(len(corners), bool), camera.K, rvec, tvec,
                                f"view#{i}"))
    return frames


@needs_onnxruntime
def test_quantize_stores_an_accepted_int8_model_and_refuses_a_worse_one(tmp_path, monkeypatch, validation_frames):
    with pytest.raises(quantize_module.QuantizeError, match="--seed 2000"):
        quantize_module.quantize(DEFAULT_WEIGHTS, tmp_path / "none", tmp_path / "x.pt", quiet=True)
    monkeypatch.setattr(quantize_module, "list_shards", lambda folder: ["shard-00000.h5"])
    monkeypatch.setattr(quantize_module, "load_frames", lambda *args, **kwargs: validation_frames)
    views = tmp_path / "views"
    views.mkdir()
    out = tmp_path / "int8.pt"
    with pytest.raises(quantize_module.QuantizeError, match="not written"):
        quantize_module.quantize(DEFAULT_WEIGHTS, views, out, calibration_frames=2, max_drop=-1.0, quiet=True)
    assert not out.exists() and list(tmp_path.iterdir()) == [views]  # a refused model leaves nothing behind
    # On these two views int8 loses at most 0.125 of a protocol's accuracy (one view's 16 corners, blur k=10;
    # 2026-11-27): accepted within twice that.
    record = quantize_module.quantize(DEFAULT_WEIGHTS, views, out, calibration_frames=2, max_drop=0.25, quiet=True)
    assert set(record["int8"]) == {"blur", "darkness"} and len(record["int8"]["blur"]) == 11
    assert record["largest_drop"] <= 0.25
    detector = Detector(weights=out)  # auto: the accepted int8 model
    assert detector.runner.name == "onnx-int8"
    # int8 in ONNX Runtime against the float weights in PyTorch (2026-11-27: point logits up to 11 apart on logits
    # up to 65; 15 of the 16 corners in common, within 0.005 px after the pattern fit)
    found, reference = detector.detect(EXAMPLE), Detector(backend="torch").detect(EXAMPLE)
    assert len(found) >= 14
    common, mine, theirs = np.intersect1d(found.ids, reference.ids, return_indices=True)
    assert len(common) >= 14 and np.abs(found.corners[mine] - reference.corners[theirs]).max() < 0.015
    image = (EXAMPLE[None, None] / np.float32(255.0)).astype(np.float32)
    int8_points, float_points = detector.runner.charuconet(image)[0], reference_points(image)
    assert np.abs(int8_points - float_points).max() < 0.4 * np.abs(float_points).max()
    with pytest.raises(quantize_module.QuantizeError, match="--force"):
        quantize_module.quantize(DEFAULT_WEIGHTS, views, out, calibration_frames=2, quiet=True)


def reference_points(image: np.ndarray) -> np.ndarray:
    """The shipped float ChArUcoNet's point logits in PyTorch."""
    return Detector(backend="torch").runner.charuconet(image)[0]


@pytest.mark.parametrize("backend", ["torch", "onnx"])
def test_points_only_runner_gives_the_same_point_logits(backend):
    if backend == "onnx" and not onnxruntime_available():
        pytest.skip("ONNX Runtime not installed")
    detector = Detector(backend=backend)
    image = (EXAMPLE[None, None] / np.float32(255.0)).astype(np.float32)
    points, ids = detector.runner.charuconet(image)
    only = make_runner(backend, detector.charuconet, None, detector.device, detector.checkpoint, points_only=True)
    only_points, no_ids = only.charuconet(image)
    assert ids is not None and ids.shape[0] == detector.charuconet.config.num_corners + 1 and no_ids is None
    np.testing.assert_allclose(only_points, points, atol=1e-5)  # runners return numpy arrays


def test_a_board_found_by_markers_runs_charuconet_without_its_id_head():
    other = BoardSpec(squares_x=7, squares_y=5, square_length=0.04, marker_length=0.03, dictionary="DICT_6X6_250")
    assert Detector(board=other).runner.charuconet(np.zeros((1, 1, 64, 64), np.float32))[1] is None
    assert Detector().runner.charuconet(np.zeros((1, 1, 64, 64), np.float32))[1] is not None


def test_detect_runs_numpy_blas_single_threaded_and_restores_it():
    def threads():  # numpy's own BLAS (other libraries loaded later, e.g. scipy's, are not the detector's)
        infos = ThreadpoolController().select(user_api="blas").info()
        return [info["num_threads"] for info in infos if "numpy" in info["filepath"]]

    if not threads():
        pytest.skip("no numpy BLAS that threadpoolctl controls")
    before = threads()
    with threadpool_limits(2, user_api="blas"):
        limited = threads()
        if max(limited) < 2:
            pytest.skip("BLAS runs one thread here whatever it is asked: nothing to limit or restore")
        detector, seen = Detector(backend="torch"), []
        run = detector.runner.charuconet

        def recording(image):
            seen.append(threads())
            return run(image)

        detector.runner.charuconet = recording
        assert len(detector.detect(EXAMPLE)) >= 15
        assert seen and all(during == [1] * len(during) for during in seen)
        assert threads() == limited
    assert threads() == before
