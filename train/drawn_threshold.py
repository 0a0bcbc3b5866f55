"""A distilled ChArUcoNet's score threshold, chosen on frames drawn for it (`train.draw`): no renders needed.

A network distilled by `train.distill` never saw a render shard, so ``train.bundle --threshold auto`` has no
validation shards to choose on; ``--threshold-data drawn`` chooses on frames drawn as its run drew its own (its
board, or ``--boards`` random boards of its ``--family``; poses, lenses, backgrounds and the paper's photometric
table) from a seed that no training step (``[seed, step]``) and no validation batch (``[val_seed, i]``) used:
``[DRAWN_SEED, i]``.

Each frame is detected whole, as `Detector.detect` does with the geometry asked for, at every threshold of
`thresholds.MARKER_THRESHOLDS` (`bundle._choose_threshold_markers` says how the low ones keep weak cells), and scored as the shard route
scores: 2 x right corners minus the corners reported (a wrong ID, > 3 px off, or any corner on a frame without a
board), so the threshold maximises right minus wrong.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from deepcharuco.boards.board import BoardSpec
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.detection.deep_detector import Detector
from deepcharuco.networks.checkpoint import read_checkpoint
from train.distill import draw_config, family_boards, parse_size
from train.draw import FrameDrawer
from train.thresholds import MARKER_THRESHOLDS, best_threshold, tally_detections

DRAWN_SEED = 2000  # distinct from a run's training seed (0) and validation seed (1000): frames neither saw
BATCH = 16


def run_boards(charuconet: str | Path) -> list[BoardSpec]:
    """The boards a `train.distill` run drew: its teacher's board, or its family's random boards."""
    checkpoint = read_checkpoint(charuconet, "charuconet")
    training = checkpoint.get("training", {})
    settings = training.get("settings", {})
    if training.get("kind") != "distill":
        raise DeepCharucoError(f"{charuconet} was not written by python -m train.distill: --threshold-data drawn is "
                               f"for distilled networks; give the run's render shards instead")
    if settings.get("family"):
        return family_boards(settings["family"], int(settings["boards"]), int(settings["seed"]))
    return [BoardSpec.from_dict(checkpoint["board"])]


def choose_threshold_drawn(charuconet: str | Path, frames: int = 192, size: str | None = None,
                           geometry: str = "markers") -> tuple[float, dict]:
    """(threshold, {threshold: right - wrong}) over ``frames`` frames drawn for the run that wrote ``charuconet`` at
    ``size`` (WxH; default the run's validation size), detected whole by a `Detector` with ``geometry``."""
    checkpoint = read_checkpoint(charuconet, "charuconet")
    settings = checkpoint.get("training", {}).get("settings", {})
    boards = run_boards(charuconet)
    frame_size = parse_size(size or settings.get("val_size", "320x240"), "--threshold-size")
    drawer = FrameDrawer(boards, draw_config(settings, frame_size))
    detectors = [Detector(board=board, weights=charuconet, refine="none", geometry=geometry) for board in boards]
    balance = dict.fromkeys(MARKER_THRESHOLDS, 0)
    with tqdm(total=frames, desc="threshold (drawn frames)", unit="frame", leave=False) as progress:
        for batch in range(-(-frames // BATCH)):
            drawn = drawer.draw(np.random.default_rng([DRAWN_SEED, batch]), min(BATCH, frames - batch * BATCH))
            images = np.rint(drawn.image[:, 0].cpu().numpy() * 255).astype(np.uint8)
            for image, board, corners, visible in zip(images, drawn.board, drawn.corners, drawn.visible):
                detector = detectors[max(int(board), 0)]  # a frame without a board: any board's detector
                count = detector.board.num_corners
                tally_detections(balance, detector, image, corners[:count].astype(np.float32) if board >= 0 else None,
                                 visible[:count])
                progress.update()
    return best_threshold(balance)
