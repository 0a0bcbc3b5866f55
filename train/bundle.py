"""Pack trained networks into one shippable file:
``python -m train.bundle --charuconet runs/charuconet/best.pt --refinenet runs/refinenet/best.pt --out runs/detector.pt``.

Use it with ``Detector(weights="runs/detector.pt")`` or ``detect --detector deep --weights runs/detector.pt``.
``--out`` has no default, and a path inside the installed package (the shipped
``deepcharuco/weights/detector.pt``, which `Detector()` loads by default) is refused unless
``--force`` is given: replacing the shipped weights is a maintainer's release step, never a
side effect. The bundle keeps the weights, architectures, board, step, run settings and
validation metrics; the optimizer state (resuming only) is dropped. ``--note key=value`` adds
free-form provenance.
``--threshold auto`` chooses the Detector's default score threshold on the ChArUcoNet run's own
validation shards (never on test data): the one that maximises right corners minus wrong ones
(a wrong ID, > 3 px off, or any corner on a frame without the board), the detections PnP gets,
decoded as ``Detector()`` decodes them (board-geometry check included: ``--geometry``); for a
points-only ChArUcoNet (``--heads points``, a family model) each frame of its own board, read by
its markers as ``Detector`` then does. A network distilled by ``train.distill`` has no shards:
``--threshold-data drawn`` chooses on frames drawn for it (`train.drawn_threshold`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import deepcharuco

import torch
from tqdm import tqdm

from datagen.shards import ShardReader
from deepcharuco.cli.common import output_file, run_command
from deepcharuco.cli.export import write_onnx_bundle
from deepcharuco.core.detection import Detection
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.detection.board_check import GEOMETRY_MODES
from deepcharuco.detection.deep_detector import Detector
from deepcharuco.detection.metrics import match_corners
from deepcharuco.networks.checkpoint import id_head_trained, read_checkpoint, save_bundle
from train.dataset import FrameDataset, split_shards
from train.drawn_threshold import choose_threshold_drawn
from train.thresholds import MARKER_THRESHOLDS, THRESHOLDS, best_threshold, tally_detections

PACKAGE_DIR = Path(deepcharuco.__file__).resolve().parent


def check_out(path: str | Path, force: bool) -> Path:
    """``--out``, checked: a writable file path, and not inside the installed package unless ``force``."""
    path = Path(path)
    if not force and path.resolve().is_relative_to(PACKAGE_DIR):
        raise DeepCharucoError(f"--out {path} is inside the installed deepcharuco package ({PACKAGE_DIR}): a bundle "
                               f"there replaces the shipped weights for every user of this installation. Write it "
                               f"elsewhere (e.g. --out runs/detector.pt, then Detector(weights=...) or detect --weights), "
                               f"or pass --force if replacing them is what you mean")
    return output_file(path)


def choose_threshold(charuconet: str | Path, data: str | None = None, max_frames: int = 300,
                     geometry: str = "repair") -> tuple[float, dict]:
    """(threshold, {threshold: right - wrong}) over the validation shards of the run that wrote ``charuconet``
    (or of ``data``), split as the trainer split them, at most ``max_frames`` frames, decoded by a `Detector`
    with board-geometry mode ``geometry``."""
    if not id_head_trained(read_checkpoint(charuconet, "charuconet")):
        geometry = "markers"  # a points-only network: its ID head is untrained, boards are read by their markers
    if geometry == "markers":
        return _choose_threshold_markers(charuconet, data, max_frames)
    detector = Detector(weights=charuconet, refine="none", geometry=geometry)
    model, board, checkpoint = detector.charuconet, detector.board, detector.checkpoint
    _, validation = _validation_shards(charuconet, checkpoint, data)
    frames = FrameDataset(validation, board, augmentation=None)
    balance = dict.fromkeys(THRESHOLDS, 0)
    for index in range(min(len(frames), max_frames)):
        frame = frames[index]
        with torch.inference_mode():
            point_logits, id_logits = model(frame["image"][None])
        height, width = frame["image"].shape[-2:]
        for threshold in THRESHOLDS:
            detector.threshold = threshold
            ids, pixels, scores = detector.decode(point_logits[0], id_logits[0], (width, height))
            if not frame["has_board"]:
                balance[threshold] -= len(ids)
                continue
            match = match_corners(Detection(ids, pixels, scores), frame["corners"].numpy(), frame["visible"].numpy())
            balance[threshold] += 2 * match.num_correct - len(ids)
    return best_threshold(balance)


def _validation_shards(charuconet: str | Path, checkpoint: dict, data: str | None) -> tuple[list[Path], list[Path]]:
    """The (train, validation) split of the shards the run that wrote ``charuconet`` trained on (or of ``data``)."""
    settings = checkpoint.get("training", {}).get("config", {})
    folder = data or settings.get("data")
    if not folder:
        raise DeepCharucoError(f"{charuconet} does not say what it was trained on: pass --threshold-data FOLDER")
    return split_shards(folder, settings.get("val_fraction", 0.1))


def _choose_threshold_markers(charuconet: str | Path, data: str | None, max_frames: int) -> tuple[float, dict]:
    """`choose_threshold` for geometry "markers": every validation frame is detected whole (its shard's board,
    read by its markers) at each of `MARKER_THRESHOLDS`, as `Detector.detect` does; the network runs once per frame
    and threshold, so fewer frames are used (a third of ``max_frames``).

    The threshold is what a corner needs to find and fit the view; the weaker cells (from
    `placement.weak_confidence`: WEAK_CONFIDENCE, or half a threshold below 2 x WEAK_CONFIDENCE) may only fill in
    corners that their found neighbours place (`placement._fill_in`, `settle_corners`). Where every cell was
    "confident" those local checks never ran: the DICT_4X4 family model, when its weak cells started at
    WEAK_CONFIDENCE whatever its threshold, chose 0.05 on its 320x240 validation frames and then put a corner two
    squares off where a 22x22 board's one view, fitted on one corner of the board, was extrapolated across a wide
    lens."""
    checkpoint = read_checkpoint(charuconet, "charuconet")
    _, validation = _validation_shards(charuconet, checkpoint, data)
    balance = dict.fromkeys(MARKER_THRESHOLDS, 0)
    budget = max(1, max_frames // 3)
    frames = [(reader, index) for reader in map(ShardReader, validation) for index in range(len(reader))][:budget]
    detectors: dict = {}  # one per board: a shard of random boards (datagen.render --family) has one per frame
    for reader, index in tqdm(frames, desc="threshold (markers)", unit="frame", leave=False):
        frame = reader[index]
        board = frame.board or reader.board_of(index)
        if board not in detectors:
            detectors[board] = Detector(board=board, weights=charuconet, refine="none", geometry="markers")
        has_board = frame.meta["has_board"]
        tally_detections(balance, detectors[board], frame.image, frame.corners if has_board else None, frame.visible)
    return best_threshold(balance)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m train.bundle", description=__doc__.splitlines()[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--charuconet", required=True, help="ChArUcoNet checkpoint (python -m train.charuconet)")
    parser.add_argument("--refinenet", required=True, help="RefineNet checkpoint (python -m train.refinenet)")
    parser.add_argument("--out", required=True,
                        help="bundle to write, e.g. runs/detector.pt (inside the installed package only with --force)")
    parser.add_argument("--force", action="store_true",
                        help="allow --out inside the installed package, e.g. replacing the shipped deepcharuco/weights/detector.pt")
    parser.add_argument("--threshold", default=None,
                        help="the Detector's default score threshold: a number, or 'auto' to choose it on the run's "
                             "validation shards (default: none stored, the Detector uses 0.3)")
    parser.add_argument("--threshold-data", default=None,
                        help="--threshold auto: frame shards to split for validation (default: the run's --data); "
                             "'drawn': frames drawn for a network distilled by python -m train.distill, from a seed "
                             "its run never drew (train.drawn_threshold)")
    parser.add_argument("--threshold-frames", type=int, default=None,
                        help="--threshold auto: at most this many validation frames (default: 300 shard frames, "
                             "192 drawn ones)")
    parser.add_argument("--geometry", choices=(*GEOMETRY_MODES, "markers"), default="repair",
                        help="--threshold auto: the Detector's board-geometry mode to choose it for ('markers' "
                             "whatever is given for a points-only ChArUcoNet, python -m train.charuconet --heads points)")
    parser.add_argument("--default-geometry", choices=(*GEOMETRY_MODES, "markers"), default=None,
                        help="how Detector decodes the weights' own board when not told (stored in the bundle; "
                             "default: none stored, 'repair' where the ID head was trained): 'markers' for a "
                             "network whose point head serves but whose ID head does not")
    parser.add_argument("--input-white", type=float, default=None,
                        help="the grey in (0, 1] that ChArUcoNet's input is brightened to where its 99th percentile "
                             "lies below it (stored in the bundle; default: none, the input as it is): 0.3 for the "
                             "distilled fast networks, chosen on drawn validation frames (docs/detector.md)")
    parser.add_argument("--note", action="append", default=[], metavar="KEY=VALUE", help="provenance to record (repeatable)")
    args = parser.parse_args(argv)
    note = {}
    for item in args.note:
        key, sep, value = item.partition("=")
        if not sep or not key:
            parser.error(f"--note {item!r}: give KEY=VALUE")
        note[key] = value
    threshold = args.threshold
    if threshold not in (None, "auto"):
        try:
            threshold = float(threshold)
        except ValueError:
            parser.error(f"--threshold {threshold!r}: give a number in (0, 1) or auto")

    def body() -> None:
        nonlocal threshold
        out = check_out(args.out, args.force)
        if threshold == "auto" and args.threshold_data == "drawn":
            geometry = args.geometry if id_head_trained(read_checkpoint(args.charuconet, "charuconet")) else "markers"
            threshold, balance = choose_threshold_drawn(args.charuconet, args.threshold_frames or 192, geometry=geometry)
            print("right - wrong corners on drawn validation frames by threshold: "
                  + ", ".join(f"{t:.2f}: {v}" for t, v in balance.items()) + f" -> {threshold:.2f}")
            if max(balance.values()) <= 0:
                print(f"warning: at no threshold did the network find more right corners than wrong ones on "
                      f"{args.threshold_frames or 192} drawn frames: it is not ready to use (train it longer)")
        elif threshold == "auto":
            threshold, balance = choose_threshold(args.charuconet, args.threshold_data, args.threshold_frames or 300,
                                                  geometry=args.geometry)
            print("right - wrong corners on validation frames by threshold: "
                  + ", ".join(f"{t:.2f}: {v}" for t, v in balance.items()) + f" -> {threshold:.2f}")
        path = save_bundle(out, args.charuconet, args.refinenet, note, threshold, args.default_geometry,
                           args.input_white)
        print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB)")
        # The same networks as ONNX beside it: Detector(weights=...) loads them where PyTorch is not installed.
        print(f"wrote {write_onnx_bundle(path)} (its ONNX bundle)")

    return run_command(body)


if __name__ == "__main__":
    sys.exit(main())
