"""deepcharuco.cli.export: TorchScript and ONNX files that reproduce PyTorch, and refusals."""

import json

import numpy as np
import pytest
import torch

from deepcharuco import BoardSpec
from deepcharuco.cli import export as export_module
from deepcharuco.cli.export import ExportError, compare, export, main
from deepcharuco.networks import ChArUcoNet, ChArUcoNetConfig, CheckpointError, RefineNet, RefineNetConfig, save_checkpoint


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    folder = tmp_path_factory.mktemp("export")
    torch.manual_seed(3)
    board = BoardSpec()
    charuconet = ChArUcoNet(ChArUcoNetConfig.lite(board.num_corners))
    refinenet = RefineNet(RefineNetConfig.lite())
    for module in (charuconet, refinenet):  # larger weights than the init: logits of realistic magnitude
        for layer in module.modules():  # (BatchNorm left at its init: x3 there too compounds to absurd logits)
            if isinstance(layer, (torch.nn.Conv2d, torch.nn.Linear)):
                layer.weight.data.mul_(3.0)
    save_checkpoint(folder / "charuconet.pt", charuconet, board=board, input_size=(96, 64))
    save_checkpoint(folder / "refinenet.pt", refinenet)
    return folder, charuconet.eval(), refinenet.eval()


def test_exports_reproduce_pytorch_on_an_image(checkpoints):
    folder, charuconet, refinenet = checkpoints
    manifest = export(folder / "charuconet.pt", folder / "out", folder / "refinenet.pt")
    assert set(manifest["networks"]) == {"charuconet", "refinenet"}
    assert json.loads((folder / "out" / "export.json").read_text())["board"] == BoardSpec().to_dict()
    # Independently of the built-in check: a size none of the checks used, through each file.
    image = torch.rand(1, 1, 72, 104)
    with torch.no_grad():
        want_points, want_ids = charuconet(image)
    got_points, got_ids = map(torch.from_numpy, export_module.run_torchscript(folder / "out" / "charuconet.ts", image.numpy()))
    assert torch.allclose(got_points, want_points, atol=1e-4) and torch.allclose(got_ids, want_ids, atol=1e-4)
    onnx_outputs, runtime = export_module.run_onnx(folder / "out" / "charuconet.onnx", image.numpy(),
                                                   export_module.network_specs((96, 64))["charuconet"])
    assert runtime == "onnxruntime"
    np.testing.assert_allclose(onnx_outputs[0], want_points.numpy(), atol=1e-4)
    np.testing.assert_allclose(onnx_outputs[1], want_ids.numpy(), atol=1e-4)
    patches = torch.rand(5, 1, 24, 24)
    with torch.no_grad():
        want = refinenet(patches).numpy()
    got, _ = export_module.run_onnx(folder / "out" / "refinenet.onnx", patches.numpy(),
                                    export_module.network_specs((96, 64))["refinenet"])
    np.testing.assert_allclose(got[0], want, atol=1e-4)


def test_onnx_also_runs_in_opencv_dnn(checkpoints, monkeypatch):
    """Without onnxruntime the check falls back to OpenCV's DNN module (a torch-free runtime users have)."""
    folder, _, _ = checkpoints
    import builtins

    real_import = builtins.__import__

    def no_onnxruntime(name, *args, **kwargs):
        if name == "onnxruntime":
            raise ImportError("hidden by the test")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_onnxruntime)
    manifest = export(folder / "charuconet.pt", folder / "dnn", folder / "refinenet.pt", formats=("onnx",))
    for network in manifest["networks"].values():
        assert network["exports"]["onnx"]["runtime_checked"] == "opencv-dnn"
        assert network["exports"]["onnx"]["max_abs_diff"] < 1e-3


def test_compare_catches_a_wrong_export():
    reference = [np.random.default_rng(0).normal(size=(2, 65, 3, 4)).astype(np.float32) * 5]
    assert compare(reference, [reference[0].copy()], "same", 1e-3) == 0.0
    shifted = reference[0] + 0.01
    with pytest.raises(ExportError, match="differ from PyTorch's by up to"):
        compare(reference, [shifted], "shifted", 1e-3)
    swapped = reference[0].copy()
    swapped[:, [0, 1]] = swapped[:, [1, 0]]  # two output channels in the wrong order
    with pytest.raises(ExportError, match="swapped classes"):
        compare(reference, [swapped], "swapped classes", 1e-3)
    with pytest.raises(ExportError, match="shape"):
        compare(reference, [reference[0][:1]], "cropped", 1e-3)


def test_cli_exports_and_refuses_bad_input(checkpoints, tmp_path, capsys):
    folder, _, _ = checkpoints
    assert main(["--weights", str(folder / "charuconet.pt"), "--out", str(tmp_path / "ts"), "--format", "torchscript"]) == 0
    assert sorted(p.name for p in (tmp_path / "ts").iterdir()) == ["charuconet.ts", "export.json"]
    assert main(["--weights", str(tmp_path / "missing.pt"), "--out", str(tmp_path / "x")]) == 2
    assert "does not exist" in capsys.readouterr().err
    # A RefineNet checkpoint where a ChArUcoNet is expected.
    with pytest.raises(CheckpointError, match="refinenet checkpoint, a charuconet was expected"):
        export(folder / "refinenet.pt", tmp_path / "y")
    with pytest.raises(ExportError, match="formats"):
        export(folder / "charuconet.pt", tmp_path / "z", formats=("tflite",))


def test_cli_refuses_an_unwritable_or_file_out_in_one_line(checkpoints, tmp_path, capsys, unwritable_dir):
    folder, _, _ = checkpoints
    (tmp_path / "a-file").write_text("")
    for out, message in ((tmp_path / "a-file", "is a file, not a folder"), (unwritable_dir / "x", "cannot write there")):
        assert main(["--weights", str(folder / "charuconet.pt"), "--out", str(out), "--format", "torchscript"]) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1, err


def test_the_fast_refinenet_runs_the_same_in_onnx_runtime(tmp_path):
    from deepcharuco.networks import load_refinenet
    from deepcharuco.networks.onnx_runner import _session
    from deepcharuco.networks.runtime import float_onnx

    torch.manual_seed(5)
    model = RefineNet(RefineNetConfig.fast())
    for layer in model.modules():  # logits of realistic magnitude, as in `checkpoints`
        if isinstance(layer, (torch.nn.Conv2d, torch.nn.Linear)):
            layer.weight.data.mul_(3.0)
    save_checkpoint(tmp_path / "fast.pt", model)
    loaded, _ = load_refinenet(tmp_path / "fast.pt")  # its architecture read back from the checkpoint, BN folded
    patches = torch.rand(7, 1, 24, 24)
    with torch.no_grad():
        want = model.eval()(patches).numpy()
    session = _session(float_onnx(loaded), 1)
    (got,) = session.run(None, {session.get_inputs()[0].name: patches.numpy()})
    np.testing.assert_allclose(got, want, atol=1e-4)
    assert np.abs(want).max() > 1.0  # not a trivially small output
