"""A board of 4 corners in 5 MP frames: how often each detector finds it, how fast, lit and dark.

    python benchmarks/small_board.py [--frames 12] [--seed 1]

A 3x3 DICT_5X5_100 board (4 corners, 4 markers) drawn at 8-15 % of the width of 2592x1944 frames of procedural
clutter (`evaluate.speed.realistic`, as `benchmarks/detect.py`'s 5 MP row draws them), then the same frames darkened
(k = 7). For OpenCV + cornerSubPix, the deep detector (the lite networks, and the fast ones with lite behind them:
``network="fast"``) and hybrid, in one run: frames found, frames whose every corner lies within 3 px of the truth,
and ms a frame. Seed 0 drew the frames the small-board rules were chosen on
(`deepcharuco.detection.markers.verification.code_errors`, `deepcharuco.detection.search_regions.board_like_boxes`);
other seeds measure.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.detection.deep_detector import Detector
from deepcharuco.detection.opencv_detector import OpenCVDetector
from evaluate.paper.protocols import darken
from evaluate.speed.realistic import Placement, clutter, with_board

TINY_BOARD = BoardSpec(squares_x=3, squares_y=3, square_length=0.04, marker_length=0.03, dictionary="DICT_5X5_100")
FIVE_MP = (2592, 1944)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    frames = [with_board(TINY_BOARD, clutter(rng, FIVE_MP), rng, Placement(0.08, 0.15), f"5MP #{i}")
              for i in range(args.frames)]
    detectors = {"opencv": OpenCVDetector(TINY_BOARD), "deep": Detector(TINY_BOARD),
                 "fast": Detector(TINY_BOARD, network="fast"), "hybrid": Detector(TINY_BOARD, mode="hybrid")}
    for light in ("lit", "dark"):
        images = [f.image if light == "lit" else darken(f.image, 7) for f in frames]
        timings = {}
        for name, detector in detectors.items():
            started, found, right = time.perf_counter(), 0, 0
            for frame, image in zip(frames, images):
                detection = detector.detect(image)
                if len(detection.ids):
                    found += 1
                    right += int(np.linalg.norm(detection.corners - frame.corners[detection.ids], axis=1).max() < 3.0)
            timings[name] = (time.perf_counter() - started) / len(frames)
            ratio = timings["opencv"] / timings[name]
            print(f"{light} {name:6s}: found {found}/{len(frames)}, right {right}, {1000 * timings[name]:.0f} ms a frame "
                  f"({ratio:.2f}x OpenCV's speed)", flush=True)


if __name__ == "__main__":
    main()
