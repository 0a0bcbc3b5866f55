"""train.drawn_threshold: a distilled network's threshold chosen on frames drawn for its run (no renders)."""

import re

import pytest
import torch

from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.networks.checkpoint import read_checkpoint
from deepcharuco.networks.shipped import DEFAULT_WEIGHTS
from train import bundle
from train.drawn_threshold import DRAWN_SEED, choose_threshold_drawn, run_boards
from train.thresholds import MARKER_THRESHOLDS


@pytest.fixture(scope="module")
def distilled(tmp_path_factory):
    """A checkpoint as train.distill writes one, holding the shipped network's weights: a student that learnt
    all its teacher knows."""
    data = read_checkpoint(DEFAULT_WEIGHTS, "charuconet")
    data["training"] = {"kind": "distill", "step": 1, "settings": {"family": None, "boards": 64, "seed": 0,
                                                                    "val_seed": 1000, "val_size": "320x240"}}
    path = tmp_path_factory.mktemp("run") / "best.pt"
    torch.save(data, path)
    return path


def test_the_threshold_is_the_best_balance_on_frames_the_run_never_drew(distilled):
    assert DRAWN_SEED not in (0, 1000)  # the run's training and validation seeds
    threshold, balance = choose_threshold_drawn(distilled, frames=6, geometry="markers")
    assert set(balance) == set(MARKER_THRESHOLDS)
    assert threshold == max(MARKER_THRESHOLDS, key=lambda t: (balance[t], t))
    # The shipped network finds the drawn boards: right corners outweigh wrong ones at the chosen threshold (a
    # drawing whose labels missed its corners, or frames not in the detector's pixels, would score <= 0).
    assert balance[threshold] >= 10, balance


def test_only_a_distilled_network_has_drawn_frames(tmp_path):
    with pytest.raises(DeepCharucoError, match="train.distill"):
        run_boards(DEFAULT_WEIGHTS)
    code = bundle.main(["--charuconet", str(DEFAULT_WEIGHTS), "--refinenet", str(DEFAULT_WEIGHTS), "--threshold",
                        "auto", "--threshold-data", "drawn", "--out", str(tmp_path / "b.pt")])
    assert code == 2 and not (tmp_path / "b.pt").exists()


def test_the_bundle_stores_the_threshold_chosen_on_drawn_frames(distilled, tmp_path, capsys):
    out = tmp_path / "detector.pt"
    assert bundle.main(["--charuconet", str(distilled), "--refinenet", str(DEFAULT_WEIGHTS), "--threshold", "auto",
                        "--threshold-data", "drawn", "--threshold-frames", "4", "--geometry", "markers",
                        "--out", str(out)]) == 0
    chosen = float(re.search(r"drawn validation frames by threshold: .* -> ([0-9.]+)", capsys.readouterr().out)[1])
    assert read_checkpoint(out, "charuconet")["threshold"] == pytest.approx(chosen)


def test_a_bundle_may_say_how_its_own_board_is_decoded(distilled, tmp_path):
    """--default-geometry markers: a network whose point head serves and whose ID head does not (a student early
    in its distillation) reads its own board by its markers unless told otherwise; without it, the ID head."""
    from deepcharuco import Detector

    out = tmp_path / "markers.pt"
    assert bundle.main(["--charuconet", str(distilled), "--refinenet", str(DEFAULT_WEIGHTS), "--threshold", "0.3",
                        "--default-geometry", "markers", "--out", str(out)]) == 0
    assert Detector(weights=out).geometry == "markers"
    assert Detector(weights=out.with_suffix(".onnx")).geometry == "markers"  # the ONNX bundle written beside it
    assert Detector(weights=out, geometry="repair").geometry == "repair"  # asked for: as asked
    assert Detector(weights=DEFAULT_WEIGHTS).geometry == "repair"
