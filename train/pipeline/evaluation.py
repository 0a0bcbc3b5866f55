"""The evaluation and bundle stages' numbers: the boards a model is evaluated on, the paper's protocols run on
them in-process (deep vs OpenCV + cornerSubPix), the bundle's speed, and what the card needs from the bundle."""

from __future__ import annotations

import time
from pathlib import Path

from deepcharuco.boards.board import BoardSpec
from deepcharuco.boards.dictionaries import MARKER_FAMILIES, marker_family
from train.pipeline.plan import Sizes, Target
from train.pipeline.records import now, slug


def evaluation_boards(target: Target) -> dict[str, BoardSpec]:
    """Boards to evaluate on: for a family, the family's boards of `evaluate.paper.unseen_boards` (or a 6x5 board of
    the family's dictionary) and, for DICT_5X5, the paper's board; for --board, that board."""
    if target.board is not None:
        return {f"{target.board.squares_x}x{target.board.squares_y} {target.board.dictionary}": target.board}
    from evaluate.paper.unseen_boards import UNSEEN_BOARDS

    dictionary = MARKER_FAMILIES[target.family][-1]  # the largest: the _50/_100/_250 ones are its prefixes
    boards = {name: board for name, board in UNSEEN_BOARDS.items() if marker_family(board.dictionary) == target.family}
    if not boards:
        boards = {f"6x5 {dictionary}": BoardSpec(squares_x=6, squares_y=5, square_length=0.04, marker_length=0.03,
                                                 dictionary=dictionary)}
    if target.family == "DICT_5X5":
        boards["5x5 DICT_5X5_50 (the paper's)"] = BoardSpec()
    return boards


def evaluate_model(weights: Path, boards: dict[str, BoardSpec], root: Path, sizes: Sizes, quiet: bool) -> dict:
    """Per board: the synthetic blur/darkness protocol and the sequences' pose accuracy, the bundle (as
    `Detector(board=...)` uses it) next to OpenCV + cornerSubPix on the same frames; and the bundle's speed."""
    from deepcharuco.detection.deep_detector import Detector
    from deepcharuco.detection.opencv_detector import OpenCVDetector
    from evaluate.paper import experiments
    from evaluate.paper.data import load_frames, select_well_lit
    from evaluate.paper.protocols import LEVELS
    from evaluate.paper.unseen_boards import board_summary

    results = {}
    for name, board in boards.items():
        frames = load_frames(root / slug(name), board)
        detectors = {"deep": Detector(board=board, weights=weights), "opencv": OpenCVDetector(board, refine="subpix")}
        well_lit = select_well_lit(frames, min(sizes.eval_images, len({f.meta.get("sequence") for f in frames})))
        synthetic = experiments.synthetic_experiment(detectors, well_lit, LEVELS, quiet)
        sequences = experiments.sequence_experiment(detectors, frames, f"sequences {name}", quiet)
        summary = board_summary(list(detectors), synthetic, sequences)
        results[name] = {"board": board.to_dict(), "geometry": detectors["deep"].geometry, "frames": len(frames),
                         "synthetic_images": len(well_lit), "summary": summary,
                         "sequences": [{"sequence": row.get("sequence"), "lux": row.get("lux"),
                                        **{d: {"pose_accuracy": row[d].get("pose_accuracy")} for d in detectors}}
                                       for row in sequences["table"]]}
        results[name]["fps_320x240"] = measure_fps(detectors["deep"], frames[:10])
    return {"boards": results, "weights": str(weights), "created": now()}


def measure_fps(detector, frames: list, seconds: float = 2.0) -> float:
    """Frames per second of detect + pose at 320x240 (frames resized to it), over ``seconds``."""
    import cv2

    images = [cv2.resize(f.image, (320, 240), interpolation=cv2.INTER_AREA) for f in frames]
    camera = frames[0].K * [[320 / frames[0].image.shape[1]], [240 / frames[0].image.shape[0]], [1]]
    done, started = 0, time.perf_counter()
    while time.perf_counter() - started < seconds or done < len(images):
        detector.estimate_pose(detector.detect(images[done % len(images)]), camera, None)
        done += 1
    return done / (time.perf_counter() - started)


def bundle_summary(path: Path) -> dict:
    """What the card needs from the bundle: the threshold, each network's steps and validation metrics."""
    from deepcharuco.networks.checkpoint import id_head_trained, read_checkpoint

    charuconet, refinenet = read_checkpoint(path, "charuconet"), read_checkpoint(path, "refinenet")
    return {"threshold": charuconet.get("threshold"), "id_head_trained": id_head_trained(charuconet),
            "charuconet": {"step": charuconet["training"].get("step"), "metrics": charuconet["training"].get("metrics")},
            "refinenet": {"step": refinenet["training"].get("step"), "metrics": refinenet["training"].get("metrics")},
            "size_mb": round(path.stat().st_size / 1e6, 2)}
