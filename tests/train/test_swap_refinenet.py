"""train.swap_refinenet: a RefineNet put into an existing ONNX bundle, its ChArUcoNets untouched."""

import json
import shutil

import numpy as np
import torch

from deepcharuco.networks import RefineNet, RefineNetConfig, save_checkpoint
from deepcharuco.networks.onnx_bundle import read_bundle
from deepcharuco.networks.onnx_runner import _session
from deepcharuco.networks.shipped import FAST_WEIGHTS_DIR
from train import swap_refinenet

FAST_BUNDLE = FAST_WEIGHTS_DIR / "detector.onnx"


def test_the_refinenet_is_swapped_and_recorded_and_the_rest_kept(tmp_path, capsys):
    bundle = tmp_path / "detector.onnx"
    shutil.copytree(FAST_BUNDLE, bundle)
    before = read_bundle(bundle)
    torch.manual_seed(2)
    model = RefineNet(RefineNetConfig.fast()).eval()
    save_checkpoint(tmp_path / "fast.pt", model)
    assert swap_refinenet.main(["--refinenet", str(tmp_path / "fast.pt"), "--bundle", str(bundle)]) == 0
    after = read_bundle(bundle)  # the recorded sha256 matches the new file
    for name in ("charuconet.onnx", "charuconet_points.onnx"):
        assert after.models[name] == before.models[name]
    assert after.models["refinenet.onnx"] != before.models["refinenet.onnx"]
    meta = json.loads((bundle / "bundle.json").read_text())
    assert meta["refinenet"]["config"]["arch"] == "fast" and meta["refinenet"]["weights"] == str(tmp_path / "fast.pt")
    assert {k: v for k, v in meta.items() if k not in ("refinenet", "models_sha256")} == \
        {k: v for k, v in before.meta.items() if k not in ("refinenet", "models_sha256")}
    patches = torch.rand(4, 1, 24, 24)
    session = _session(after.models["refinenet.onnx"], 1)
    (got,) = session.run(None, {session.get_inputs()[0].name: patches.numpy()})
    with torch.no_grad():
        np.testing.assert_allclose(got, model(patches).numpy(), atol=1e-4)


def test_the_shipped_bundles_and_a_damaged_one_are_refused(tmp_path, capsys):
    torch.manual_seed(2)
    save_checkpoint(tmp_path / "fast.pt", RefineNet(RefineNetConfig.fast()))
    assert swap_refinenet.main(["--refinenet", str(tmp_path / "fast.pt"), "--bundle", str(FAST_BUNDLE)]) == 2
    assert "inside the installed deepcharuco package" in capsys.readouterr().err
    bundle = tmp_path / "detector.onnx"
    shutil.copytree(FAST_BUNDLE, bundle)
    (bundle / "charuconet.onnx").write_bytes(b"truncated")
    kept = (bundle / "refinenet.onnx").read_bytes()
    assert swap_refinenet.main(["--refinenet", str(tmp_path / "fast.pt"), "--bundle", str(bundle)]) == 2
    assert "charuconet.onnx" in capsys.readouterr().err
    assert (bundle / "refinenet.onnx").read_bytes() == kept  # nothing written into a damaged bundle
