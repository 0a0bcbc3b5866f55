"""Where the shipped weights lie in the installed package (no PyTorch needed to name them)."""

from __future__ import annotations

from pathlib import Path

from deepcharuco.core.checks import check_choice
from deepcharuco.core.errors import DeepCharucoError, OptionError

WEIGHTS_DIR = Path(__file__).resolve().parents[1] / "weights"  # deepcharuco/weights: package data
DEFAULT_WEIGHTS = WEIGHTS_DIR / "detector.pt"  # the paper's board: ChArUcoNet (ID head included) + RefineNet
# Family models (`train.pipeline --family F`): weights/families/DICT_4X4.pt ..., point head trained on random
# boards of the family; `Detector()` loads the one of the board's family (`deep_detector.shipped_weights`).
FAMILY_WEIGHTS_DIR = WEIGHTS_DIR / "families"
# The distilled fast ChArUcoNets (issue 51, `train.distill --arch fast`): the same layout (detector.onnx/,
# families/<FAMILY>.onnx/) as ONNX bundles alone, so they run on the CPU through ONNX Runtime, where the network
# is the cost; on a GPU the lite network is under a millisecond a frame and the decoding is the cost.
FAST_WEIGHTS_DIR = WEIGHTS_DIR / "fast"
# Detector(network=...), deepcharuco detect/calibrate --network. "auto": the fast networks first, the lite ones
# wherever those find too little (`deep_detector.Detector`'s ``network``).
NETWORKS = ("lite", "fast", "auto")


def fast_networks_shipped() -> bool:
    """Whether this version ships the fast networks (`FAST_WEIGHTS_DIR`)."""
    return (FAST_WEIGHTS_DIR / "detector.onnx" / "bundle.json").is_file()


def default_network(weights: str | Path | None, device: str = "cpu", backend: str = "auto") -> str:
    """The command line's network where ``--network`` is not given: "auto" for the shipped weights in ONNX Runtime on
    the CPU, else "lite" (a user's ``weights``; a GPU, where the lite network takes under a millisecond a frame;
    ``backend`` "torch" or "onnx-int8", which the fast networks' float32 ONNX bundles do not run in; a version
    without the fast networks)."""
    onnx = backend in ("auto", "onnx")
    return "auto" if weights is None and str(device) == "cpu" and onnx and fast_networks_shipped() else "lite"


def network_weights(network: str, weights: str | Path | None, device: str = "cpu") -> str | Path | None:
    """The weights a detector reads for ``network`` (`NETWORKS`): ``weights`` for "lite" (None: the shipped lite
    networks), the shipped fast networks' folder (`FAST_WEIGHTS_DIR`) for "fast" and "auto"."""
    check_choice("network", network, NETWORKS)
    if network == "lite":
        return weights
    if weights is not None:
        raise OptionError(f"give weights or network={network!r}, not both: network names shipped weights")
    if str(device) != "cpu":
        raise OptionError(f"network={network!r} ships as ONNX bundles, which run on the CPU; on a GPU the lite "
                          f"network takes under a millisecond a frame: leave network out there, or use device='cpu'")
    if not fast_networks_shipped():
        raise DeepCharucoError(f"network={network!r}: this version ships no fast networks ({FAST_WEIGHTS_DIR} is "
                               f"missing); leave network out for the lite ones")
    return FAST_WEIGHTS_DIR
