"""ChArUcoNet's dim inputs brightened for the networks whose bundle says so (``input_white``: the shipped fast ones)."""

import json
import shutil

import numpy as np
import pytest

from conftest import VIEW_POSES, make_view
import deepcharuco.detection.deep_detector as deep_detector
from deepcharuco import BoardSpec
from deepcharuco.detection.deep_detector import Detector
from deepcharuco.detection.levels import brightness_gain, network_input
from deepcharuco.geometry.camera import Camera
from deepcharuco.networks.onnx_bundle import BundleError, read_bundle
from deepcharuco.networks.runtime import onnxruntime_available
from deepcharuco.networks.shipped import FAST_WEIGHTS_DIR
from evaluate.paper.protocols import darken

BOARD = BoardSpec(squares_x=7, squares_y=5, square_length=0.04, marker_length=0.03, dictionary="DICT_6X6_250")


def test_a_dim_input_is_brightened_to_the_white_and_a_bright_one_left_as_it_is():
    rng = np.random.default_rng(0)
    dim = rng.integers(0, 21, (48, 64)).astype(np.uint8)  # greys 0-20: the 99th percentile is 20
    rank = int(0.99 * (dim.size - 1))
    percentile = np.sort(dim.ravel())[rank]
    assert brightness_gain(dim, 0.3) == pytest.approx(0.3 * 255 / percentile)
    brightened = network_input(dim, 0.3)[0, 0]
    assert np.sort(brightened.ravel())[rank] == pytest.approx(0.3, abs=1e-6)
    np.testing.assert_allclose(brightened, dim * (0.3 * 255 / percentile) / 255, rtol=1e-6)
    lamp = dim.copy()
    lamp[0, :20] = 200  # 20 of 3,072 pixels (under 1 %): the percentile stays dim, the lamp is clipped, not wrapped
    assert brightness_gain(lamp, 0.3) == brightness_gain(dim, 0.3)
    np.testing.assert_array_equal(network_input(lamp, 0.3)[0, 0, 0, :20], 1.0)
    black = np.zeros((16, 16), np.uint8)
    assert network_input(black, 0.3).max() == 0.0  # nothing to brighten: no division by a zero percentile

    bright = rng.integers(0, 256, (48, 64)).astype(np.uint8)
    assert brightness_gain(bright, 0.3) == 1.0 and brightness_gain(dim, None) == 1.0
    # unchanged to the bit where no gain applies: the lite networks' inputs are those they always were
    np.testing.assert_array_equal(network_input(bright, 0.3), network_input(bright))
    np.testing.assert_array_equal(network_input(bright), bright[None, None] / np.float32(255.0))


@pytest.mark.skipif(not onnxruntime_available(), reason="ONNX Runtime not installed")
def test_the_fast_networks_find_a_board_in_near_darkness_only_with_their_input_brightened():
    """A frontal 320x240 view at the paper's darkness k = 8 (a white paper at 4 grey levels): the fast networks read
    all 24 corners with the bundle's ``input_white``, none without it (their confidences stay under the threshold)."""
    camera = Camera.from_fov(320, 240, hfov_deg=60.0)
    image, _, _, truth = make_view(BOARD, camera, **VIEW_POSES[0])
    dark = darken(image, 8)
    assert np.percentile(dark, 99) <= 5
    fast = Detector(BOARD, network="fast")
    assert fast.input_white == 0.3 and fast.backup.input_white is None  # the lite networks' input as it is
    # a stream's frame: with "fast" the lite networks never search it (`WHOLE_BACKUP`), the fast ones answer alone
    found = fast.detect(dark, stream=True)
    assert len(found) == BOARD.num_corners
    assert np.abs(found.corners - truth[found.ids]).max() < 0.3
    fast.input_white = None
    assert len(fast.detect(dark, stream=True)) == 0


@pytest.mark.skipif(not onnxruntime_available(), reason="ONNX Runtime not installed")
def test_a_tracked_crop_is_not_brightened(monkeypatch):
    """Where the board is expected (a `BoardTracker`'s crop) the input stays as it is: brightened crops put corners
    3-10 px off on caliscope's darkened videos (docs/detector.md); a whole frame is brightened."""
    camera = Camera.from_fov(320, 240, hfov_deg=60.0)
    image, _, _, _ = make_view(BOARD, camera, **VIEW_POSES[1])
    dark = darken(image, 8)
    fast = Detector(BOARD, network="fast")
    whites = []
    network_input = deep_detector.network_input
    monkeypatch.setattr(deep_detector, "network_input", lambda gray, white=None: whites.append(white)
                        or network_input(gray, white))
    found = fast.detect(dark, stream=True)
    assert len(found) == BOARD.num_corners and set(whites) == {0.3}
    whites.clear()
    assert len(fast.detect(dark, expected=found)) == BOARD.num_corners
    assert whites and set(whites) == {None}


def test_a_bundles_input_white_must_be_a_grey(tmp_path):
    bundle = tmp_path / "detector.onnx"
    shutil.copytree(FAST_WEIGHTS_DIR / "detector.onnx", bundle)
    meta = json.loads((bundle / "bundle.json").read_text())
    assert meta["input_white"] == 0.3
    meta["input_white"] = 2.5
    (bundle / "bundle.json").write_text(json.dumps(meta))
    with pytest.raises(BundleError, match="input_white 2.5 is not a grey"):
        Detector(BOARD, weights=bundle)
    assert read_bundle(bundle).meta["input_white"] == 2.5  # read as it is; the Detector refuses it
