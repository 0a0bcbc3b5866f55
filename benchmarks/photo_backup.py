"""Which photos the lite networks rescue behind the fast ones, and what the fast search saw there: the validation that
chose `deep_detector.BACKUP_MIN_CELLS` (docs/detector.md, "A lit photo's lite search only where the fast networks saw
corners").

    python benchmarks/photo_backup.py [--seed 1] [--count 480] [--out runs/photo_backup.json]

Frames (seed ``--seed``; the report and `benchmarks/detect.py` draw others): five boards (the paper's 5x5 DICT_5X5_50,
4x5 DICT_4X4_50 inverted, 12x9 and 16x16 DICT_4X4_1000, 7x5 DICT_6X6_250) at 1280x720, 720x540 and 640x480 on
procedural clutter (`evaluate.speed.realistic`), in turn: tilted 55-72 degrees about one axis, cut by the frame's edge,
both, defocused, steep and defocused, small (6-15 % of the width), steep and dim (darkness k = 5-8), no board.

For each frame `Detector(board, network="auto")`'s fast search alone (`_detect`: its detection and what it saw,
`levels.Seen`), and, where it found fewer than 4 corners, the lite networks' whole search (`backup`), scored against
the truth (3 px). Printed: lite's rescues (>= 4 right corners where the fast networks had fewer) and the fast search's
corner-like cells in them and in the searches that found nothing, for each gate; then the reported corners more than
3 px from their truth, and how many lie nearer another corner's truth (a wrong ID). ``--out``: every frame's numbers.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from deepcharuco import BoardSpec
from deepcharuco.boards.synthetic import look_at_pose
from deepcharuco.detection.deep_detector import Detector
from deepcharuco.detection.tracking import MIN_CORNERS as MIN_TRACKED_CORNERS
from deepcharuco.geometry.pose import project_corners
from evaluate.paper.protocols import CORRECT_RADIUS_PX, TestFrame, darken, score_corners
from evaluate.speed.realistic import board_layer, clutter, webcam_K

BOARDS = {
    "paper 5x5": BoardSpec(),
    "4x5 DICT_4X4 inverted": BoardSpec(4, 5, 0.054, 0.0405, "DICT_4X4_50", inverted=True),
    "12x9 DICT_4X4": BoardSpec(12, 9, 0.02, 0.015, "DICT_4X4_1000"),
    "16x16 DICT_4X4": BoardSpec(16, 16, 0.01, 0.0075, "DICT_4X4_1000"),
    "7x5 DICT_6X6": BoardSpec(7, 5, 0.03, 0.022, "DICT_6X6_250"),
}
SIZES = ((1280, 720), (720, 540), (640, 480))
CONDITIONS = ("steep", "edge", "defocus", "small", "steep+defocus", "edge+steep", "dim+steep", "none")
GATES = (1, 2, 3, 4, 5, 6)


def draw(board: BoardSpec, size: tuple[int, int], condition: str, rng: np.random.Generator) -> TestFrame:
    """A frame of ``size`` (W, H): ``board`` drawn into procedural clutter as ``condition`` says (module docstring);
    truth: the projected corners, those inside the frame visible."""
    width, height = size
    K = webcam_K(size)
    background = clutter(rng, size)
    if condition == "none":
        return TestFrame(background, np.zeros((0, 2), np.float32), np.zeros(0, bool), K, name=condition)
    share = rng.uniform(0.06, 0.15) if condition == "small" else rng.uniform(0.25, 0.8)
    if "edge" in condition:
        share = rng.uniform(0.4, 1.0)
    distance = K[0, 0] * max(board.size_m) / (share * width)
    tilt = rng.uniform(-35, 35, 2)
    if "steep" in condition:
        axis = rng.integers(0, 2)
        tilt[axis] = rng.choice([-1, 1]) * rng.uniform(55, 72)
    roll = rng.uniform(-40, 40)
    reach = 0.5 * (np.array([width, height]) - share * width) * distance / K[0, 0]
    offset = rng.uniform(-1, 1, 2) * np.maximum(reach, 0)
    if "edge" in condition:  # the board's centre 75-105 % of the way to an edge: part of it out of the frame
        half = 0.5 * np.array([width, height]) * distance / K[0, 0]
        axis = rng.integers(0, 2)
        offset[axis] = rng.choice([-1, 1]) * half[axis] * rng.uniform(0.75, 1.05)
    rvec, tvec = look_at_pose(board, distance, tilt[0], tilt[1], roll, tuple(offset))
    drawn, coverage = board_layer(board, K, rvec, tvec, size, 4)
    image = drawn * rng.uniform(0.55, 1.0) + background.astype(np.float32) * (1 - coverage)
    if "defocus" in condition:
        image = cv2.GaussianBlur(image, (0, 0), rng.uniform(1.5, 4.0) * width / 1280)
    image += rng.normal(0, 2.0, image.shape).astype(np.float32)
    image = np.clip(np.rint(image), 0, 255).astype(np.uint8)
    if "dim" in condition:
        image = darken(image, int(rng.integers(5, 9)))
    corners = project_corners(board, rvec, tvec, K).astype(np.float32)
    inside = (corners >= 0.5).all(axis=1) & (corners[:, 0] <= width - 1.5) & (corners[:, 1] <= height - 1.5)
    return TestFrame(image, corners, inside, K, np.ravel(rvec), np.ravel(tvec), condition)


def wrong_ids(detection, frame: TestFrame) -> tuple[int, int]:
    """(corners more than 3 px from their truth, those of them nearer another corner's truth than their own)."""
    if len(detection) == 0:
        return 0, 0
    far = np.linalg.norm(detection.corners - frame.corners[detection.ids], axis=1) > CORRECT_RADIUS_PX
    nearest = np.linalg.norm(detection.corners[far][:, None] - frame.corners[None], axis=2).argmin(axis=1)
    return int(far.sum()), int((nearest != detection.ids[far]).sum())


def measure(seed: int, count: int) -> list[dict]:
    rng = np.random.default_rng(seed)
    detectors = {name: Detector(board, network="auto") for name, board in BOARDS.items()}
    rows = []
    for index in tqdm(range(count), desc="frames", unit="frame"):
        name = list(BOARDS)[index % len(BOARDS)]
        size = SIZES[(index // len(BOARDS)) % len(SIZES)]
        condition = CONDITIONS[(index // (len(BOARDS) * len(SIZES))) % len(CONDITIONS)]
        frame = draw(BOARDS[name], size, condition, rng)
        detector = detectors[name]
        fast, seen = detector._detect(frame.image, None)
        lite = detector.backup.detect(frame.image) if len(fast) < MIN_TRACKED_CORNERS else None
        final = detector.detect(frame.image)
        rows.append({"index": index, "board": name, "size": list(size), "condition": condition, "dim": seen.dim,
                     "corner_cells": seen.corner_cells, "fast_right": score_corners(fast, frame).num_correct,
                     "lite_right": None if lite is None else score_corners(lite, frame).num_correct,
                     "reported": len(final), "right": score_corners(final, frame).num_correct,
                     "wrong": wrong_ids(final, frame)})
    return rows


def summary(rows: list[dict]) -> None:
    searched = [r for r in rows if r["lite_right"] is not None]
    rescued = [r for r in searched if r["lite_right"] >= 4 and r["fast_right"] < 4]
    print(f"{len(rows)} frames; the fast networks found < {MIN_TRACKED_CORNERS} corners in {len(searched)} "
          f"({sum(r['dim'] for r in searched)} dim); lite rescued {len(rescued)} ({sum(r['dim'] for r in rescued)} dim)")
    lit, lit_rescued = [r for r in searched if not r["dim"]], [r for r in rescued if not r["dim"]]
    print("corner-like cells in the lit rescues:", sorted(r["corner_cells"] for r in lit_rescued))
    for gate in GATES:
        kept = sum(r["corner_cells"] >= gate for r in lit_rescued)
        skipped = sum(r["corner_cells"] < gate for r in lit if r not in lit_rescued)
        print(f"  gate {gate}: lit rescues kept {kept} of {len(lit_rescued)}, lite searches skipped {skipped} of "
              f"{len(lit)} lit")
    far, other = sum(r["wrong"][0] for r in rows), sum(r["wrong"][1] for r in rows)
    print(f"reported {sum(r['reported'] for r in rows)} corners, {sum(r['right'] for r in rows)} right; {far} more "
          f"than {CORRECT_RADIUS_PX:g} px off in {sum(r['wrong'][0] > 0 for r in rows)} frames, {other} of them nearer "
          f"another corner's truth (a wrong ID) in {sum(r['wrong'][1] > 0 for r in rows)} frames")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, default=1, help="the frames' rng seed (default 1)")
    parser.add_argument("--count", type=int, default=480, help="frames; 120 go once through every board, size and "
                                                               "condition (default 480)")
    parser.add_argument("--out", type=Path, default=None, help="write every frame's numbers here (JSON)")
    args = parser.parse_args()
    if args.count < 1:
        parser.error(f"--count must be >= 1, got {args.count}")
    rows = measure(args.seed, args.count)
    summary(rows)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(rows))


if __name__ == "__main__":
    main()
