"""ChArUcoNet / RefineNet: sizes, label encodings and their sub-pixel conventions, checkpoints, the Detector's plumbing."""

import copy
from pathlib import Path

import numpy as np
import pytest
import torch

from deepcharuco import BoardSpec, DeepCharucoError
from deepcharuco.detection.deep_detector import Detector
from deepcharuco.detection.levels import PATCH_ORIGIN
from deepcharuco.networks import (
    ChArUcoNet, ChArUcoNetConfig, CheckpointError, fold_batch_norm, RefineNet, RefineNetConfig, cell_to_offset, decode_offsets,
    load_charuconet, offset_to_cell, save_checkpoint,
)
from deepcharuco.networks.cells import decode_cells, encode_cells
from deepcharuco.networks.runtime import TorchRunner


def megabytes(model):
    return sum(p.numel() for p in model.parameters()) * 4 / 2**20


def test_sizes_match_the_paper():
    assert 4.6 < megabytes(ChArUcoNet(ChArUcoNetConfig.paper())) < 4.9  # paper: 4.8 MB
    assert 4.0 < megabytes(RefineNet(RefineNetConfig.paper())) < 4.2  # paper: 4.1 MB
    assert megabytes(ChArUcoNet(ChArUcoNetConfig.lite())) < 1.0
    points, ids = ChArUcoNet(ChArUcoNetConfig(num_corners=24))(torch.zeros(2, 1, 240, 320))
    assert points.shape == (2, 65, 30, 40) and ids.shape == (2, 25, 30, 40)
    assert RefineNet()(torch.zeros(3, 1, 24, 24)).shape == (3, 4096)


def perfect_logits(points, ids, num_corners):
    rows, cols = points.shape
    point_logits = torch.full((65, rows, cols), -20.0)
    id_logits = torch.full((num_corners + 1, rows, cols), -20.0)
    r, c = np.indices(points.shape)
    point_logits[points.ravel(), r.ravel(), c.ravel()] = 20.0
    id_logits[ids.ravel(), r.ravel(), c.ravel()] = 20.0
    return point_logits, id_logits


def test_corner_decodes_back_within_a_sixteenth_of_a_pixel():
    """corner -> cell labels -> decoded pixel -> RefineNet patch offset -> grid cell -> decoded: < 1/16 px per axis."""
    rng = np.random.default_rng(0)
    corners = rng.uniform(0, [319.4, 239.4], size=(16, 2)).astype(np.float32)
    corners[:, 0] = np.sort(corners[:, 0]) + np.arange(16) * 0.0  # distinct cells almost surely
    points, ids = encode_cells(corners, np.ones(16, bool), 240, 320)
    found_ids, pixels, scores = decode_cells(*perfect_logits(points, ids, 16), threshold=0.5)
    kept = {int(i) for i in found_ids}
    assert len(kept) >= 15 and np.all(scores > 0.99)  # two corners may share a cell
    for corner_id, pixel in zip(found_ids, pixels):
        assert np.all(np.abs(pixel - corners[corner_id]) <= 0.5 + 1e-6)
        offset = torch.from_numpy(corners[corner_id] - (pixel - PATCH_ORIGIN))
        assert torch.all((offset >= 7.5) & (offset < 15.5))
        decoded = cell_to_offset(offset_to_cell(offset)) + torch.from_numpy(pixel - PATCH_ORIGIN)
        assert torch.all(torch.abs(decoded - torch.from_numpy(corners[corner_id])) <= 1 / 16 + 1e-5)


def test_refinenet_grid_convention():
    """Cell j covers [7.5 + j/8, 7.5 + (j+1)/8): the centre pixel 12 of a patch is cells 36 and 35's border."""
    assert offset_to_cell(torch.tensor([7.5, 7.5])) == 0
    assert offset_to_cell(torch.tensor([15.49, 15.49])) == 64 * 64 - 1
    assert offset_to_cell(torch.tensor([12.0, 12.0])) == 36 * 64 + 36
    np.testing.assert_allclose(cell_to_offset(torch.tensor(36 * 64 + 36)), [12.0625, 12.0625])
    offsets = torch.rand(1000, 2) * 8 + 7.5
    assert torch.abs(cell_to_offset(offset_to_cell(offsets)) - offsets).max() <= 1 / 16 + 1e-6


def test_soft_argmax_recovers_an_off_grid_peak():
    true = torch.tensor([[11.37, 9.81], [14.02, 8.4]])
    centres = cell_to_offset(torch.arange(4096))  # (4096, 2)
    logits = -((centres[None] - true[:, None]) ** 2).sum(-1) / (2 * 0.06**2)
    assert torch.abs(decode_offsets(logits, soft_radius=3) - true).max() < 0.01
    assert torch.abs(decode_offsets(logits, soft_radius=0) - true).max() <= 1 / 16


def test_checkpoints_from_before_batch_norm_still_load(tmp_path):
    """Format-1 files written before ``batch_norm`` existed describe plain networks and load as such."""
    plain = ChArUcoNet(ChArUcoNetConfig(widths=(8, 8, 8, 8), head=8, batch_norm=False))
    save_checkpoint(tmp_path / "old.pt", plain, board=BoardSpec(), input_size=(320, 240))
    data = torch.load(tmp_path / "old.pt", weights_only=True)
    del data["config"]["batch_norm"]
    torch.save(data, tmp_path / "old.pt")
    model, _, _ = load_charuconet(tmp_path / "old.pt")
    assert not model.config.batch_norm and not any(isinstance(m, torch.nn.BatchNorm2d) for m in model.modules())
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in ChArUcoNet(ChArUcoNetConfig.lite()).modules())
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in RefineNet(RefineNetConfig.lite()).modules())


def test_folding_batch_norm_keeps_the_outputs():
    torch.manual_seed(0)
    for model, shape in ((ChArUcoNet(ChArUcoNetConfig.lite()), (2, 1, 64, 80)), (RefineNet(RefineNetConfig.lite()), (5, 1, 24, 24)),
                         (RefineNet(RefineNetConfig.fast()), (5, 1, 24, 24))):
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm2d):  # statistics as after training, not the identity of a fresh layer
                m.running_mean.uniform_(-0.5, 0.5), m.running_var.uniform_(0.5, 2.0), m.weight.data.uniform_(0.5, 1.5)
        x = torch.rand(shape)
        with torch.no_grad():
            before = model.eval()(x)
            folded = fold_batch_norm(model)
            after = folded(x)
        assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in folded.modules())
        for a, b in zip(before if isinstance(before, tuple) else (before,), after if isinstance(after, tuple) else (after,)):
            assert torch.allclose(a, b, atol=1e-4, rtol=1e-4)
    with pytest.raises(ValueError, match="eval mode"):
        fold_batch_norm(RefineNet(RefineNetConfig.lite()).train())


def test_the_fast_refinenet_has_the_same_output_for_a_third_of_the_multiply_adds():
    multiply_adds = {}
    for name in ("lite", "fast"):
        model, total = RefineNet(getattr(RefineNetConfig, name)()).eval(), []

        def count(module, inputs, output):
            if isinstance(module, torch.nn.Conv2d):
                total.append(output.numel() * module.in_channels * module.kernel_size[0] * module.kernel_size[1])
            elif isinstance(module, torch.nn.Linear):
                total.append(module.in_features * module.out_features)

        hooks = [m.register_forward_hook(count) for m in model.modules()]
        with torch.no_grad():
            assert model(torch.rand(1, 1, 24, 24)).shape == (1, 4096)  # one patch
        [h.remove() for h in hooks]
        multiply_adds[name] = sum(total)
    assert multiply_adds["fast"] < 0.4 * multiply_adds["lite"], multiply_adds
    fast = RefineNetConfig.fast()
    assert RefineNetConfig.from_dict(fast.to_dict()) == fast and fast.to_dict()["arch"] == "fast"
    assert "arch" not in RefineNetConfig.lite().to_dict()  # the shipped lite files stay as they were
    with pytest.raises(ValueError, match="3 widths"):
        RefineNetConfig(widths=(16, 32, 48, 64), arch="fast")
    with pytest.raises(ValueError, match="arch"):
        RefineNetConfig(arch="xfeat")


def test_gaussian_targets_peak_at_the_label_cell_and_centre_on_the_offset():
    from train.refinenet import gaussian_targets
    offsets = torch.tensor([[7.51, 15.49], [11.3, 9.87], [12.01, 12.04]])
    targets = gaussian_targets(offsets, 2.0)
    assert targets.shape == (3, 4096) and torch.allclose(targets.sum(1), torch.ones(3))
    assert torch.equal(targets.argmax(1), offset_to_cell(offsets))
    mean = (targets[:, :, None] * cell_to_offset(torch.arange(4096))[None]).sum(1)
    assert torch.allclose(mean[1:], offsets[1:], atol=1e-3)  # away from the grid's edges, the mean is the offset


def test_encoding_skips_invisible_and_outside_corners():
    corners = np.array([[5.2, 5.0], [400.0, 10.0], [40.0, 40.0], [np.nan, np.nan]], np.float32)
    points, ids = encode_cells(corners, np.array([True, True, False, True]), 240, 320)
    assert (points < 64).sum() == 1 and ids[0, 0] == 0 and points[0, 0] == 5 * 8 + 5
    assert np.all(ids[points == 64] == 4)


def test_checkpoint_errors(tmp_path):
    board = BoardSpec()
    net = ChArUcoNet(ChArUcoNetConfig.lite())
    path = save_checkpoint(tmp_path / "net.pt", net, board=board, input_size=(320, 240))
    model, loaded_board, _ = load_charuconet(path)
    assert loaded_board == board
    for a, b in zip(model.state_dict().values(), fold_batch_norm(copy.deepcopy(net).eval()).state_dict().values()):
        assert torch.equal(a, b)
    with pytest.raises(CheckpointError, match="does not exist"):
        load_charuconet(tmp_path / "missing.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint at all")
    with pytest.raises(CheckpointError, match="not a readable PyTorch checkpoint"):
        load_charuconet(tmp_path / "junk.pt")
    torch.save({"weights": torch.zeros(3)}, tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match="not a Deep ChArUco checkpoint"):
        load_charuconet(tmp_path / "other.pt")
    other_board = BoardSpec(squares_x=7, squares_y=5, dictionary="DICT_6X6_250")
    with pytest.raises(CheckpointError, match="was trained for"):
        load_charuconet(path, board=other_board)
    refine = save_checkpoint(tmp_path / "refine.pt", RefineNet(RefineNetConfig.lite()))
    with pytest.raises(CheckpointError, match="refinenet checkpoint, a charuconet was expected"):
        load_charuconet(refine)
    data = torch.load(path, weights_only=True)
    data["config"] = ChArUcoNetConfig.paper().to_dict()  # weights of the lite net under the paper's architecture
    torch.save(data, tmp_path / "mismatch.pt")
    with pytest.raises(CheckpointError, match="do not fit the architecture"):
        load_charuconet(tmp_path / "mismatch.pt")
    with pytest.raises(DeepCharucoError, match="ChArUcoNet checkpoint needs the BoardSpec"):
        save_checkpoint(tmp_path / "x.pt", net)


class OneHotRefineNet(torch.nn.Module):
    """Stands in for RefineNet: always answers the cell of a fixed offset."""

    def __init__(self, offset):
        super().__init__()
        self.cell = offset_to_cell(torch.tensor(offset))

    def forward(self, patches):
        logits = torch.full((len(patches), 4096), -30.0)
        logits[:, self.cell] = 30.0
        return logits


def test_detector_plumbing(tmp_path, default_views):
    """A random-weight ChArUcoNet with threshold 0, decoded as the paper decodes (its random IDs fit no view
    of the board, so the checked decodings rightly report nothing), reports some IDs, each once; RefineNet
    offsets land at candidate pixel - 12 + offset; all refine modes run."""
    torch.manual_seed(0)
    board = BoardSpec()
    weights = save_checkpoint(tmp_path / "c.pt", ChArUcoNet(ChArUcoNetConfig.lite()), board=board, input_size=(320, 240))
    refine = save_checkpoint(tmp_path / "r.pt", RefineNet(RefineNetConfig.lite()))
    image = default_views[0][0][:237, :315]  # not a multiple of 8
    results = {}
    for mode in ("none", "subpix", "refinenet"):
        detector = Detector(weights=weights, refine=mode, refine_weights=refine, threshold=0.0, geometry="none")
        results[mode] = detector.detect(image)
        d = results[mode]
        assert 1 <= len(d) <= 16 and d.corners.dtype == np.float32
        assert np.array_equal(d.ids, results["none"].ids)
        assert np.all((d.corners >= -1) & (d.corners < [316, 238]))
    detector = Detector(weights=weights, refine="refinenet", refine_weights=refine, threshold=0.0, soft_radius=0,
                        geometry="none")
    detector.runner = TorchRunner(detector.charuconet, OneHotRefineNet([13.3, 10.7]), detector.device)
    refined = detector.detect(image)
    expected = results["none"].corners - PATCH_ORIGIN + cell_to_offset(offset_to_cell(torch.tensor([13.3, 10.7]))).numpy()
    np.testing.assert_allclose(refined.corners, expected, atol=1e-5)
    with pytest.raises(ValueError, match="refine must be one of"):
        Detector(weights=weights, refine="magic")
    with pytest.raises(CheckpointError, match="holds no refinenet|charuconet checkpoint, a refinenet"):
        Detector(weights=weights, refine="refinenet")


def test_a_failed_save_leaves_the_old_file_and_no_temporary(tmp_path, monkeypatch):
    from deepcharuco.networks import checkpoint

    target = tmp_path / "detector.pt"
    target.write_bytes(b"old weights")

    def full_disk(data, file):
        Path(file).write_bytes(b"half")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(checkpoint.torch, "save", full_disk)
    with pytest.raises(OSError, match="No space left"):
        checkpoint.save_atomically({"x": 1}, target)
    assert target.read_bytes() == b"old weights" and [p.name for p in tmp_path.iterdir()] == ["detector.pt"]
