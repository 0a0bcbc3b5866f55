"""Where the shipped weights lie in the installed package (no PyTorch needed to name them)."""

from pathlib import Path

WEIGHTS_DIR = Path(__file__).resolve().parents[1] / "weights"  # deepcharuco/weights: package data
DEFAULT_WEIGHTS = WEIGHTS_DIR / "detector.pt"  # the paper's board: ChArUcoNet (ID head included) + RefineNet
# Family models (`train.pipeline --family F`): weights/families/DICT_4X4.pt ..., point head trained on random
# boards of the family; `Detector()` loads the one of the board's family (`deep_detector.shipped_weights`).
FAMILY_WEIGHTS_DIR = WEIGHTS_DIR / "families"
