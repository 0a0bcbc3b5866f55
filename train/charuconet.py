"""Train ChArUcoNet on rendered shards: ``python -m train.charuconet --data data/renders --out runs/charuconet``.

Loss: cross-entropy on the 65-way point labels plus on the (N+1)-way ID labels of every 8x8
cell; ``--id-positive-weight w`` weights the cells holding a corner w times in the ID term
(the point head learns "corner here" within a few hundred steps, while the ID head, whose
corner cells are ~2 % of all cells, stayed near chance for thousands of steps on a CPU run).
Validation: the paper's corner accuracy (right ID within 3 px, / N corners) on the validation
shards' positives, detections on negatives, and the loss.

``--heads points`` trains the point head alone (the ID term is dropped) on shards of any boards,
e.g. random boards of one marker family: the ID head of such a network could only learn one board,
and `Detector` finds every board from the point head's corners and the board's markers
("markers"). Its checkpoint records ``heads: "points"``; validation is then the point head's F1
(corners found within 3 px, any ID, at point confidence >= 0.5).
"""

from __future__ import annotations

import sys
from dataclasses import replace

import numpy as np
import torch
import torch.nn.functional as F

from datagen.shards import ShardReader
from deepcharuco.boards.board import BoardSpec
from deepcharuco.core.detection import Detection
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.detection.metrics import match_corners
from deepcharuco.networks.cells import decode_cells, point_candidates
from deepcharuco.networks.charuconet import ChArUcoNet, ChArUcoNetConfig
from deepcharuco.networks.checkpoint import HEADS, read_checkpoint
from train.augment import AugmentConfig
from train.cli import parse_crop, run_trainer
from train.dataset import FrameDataset, split_shards
from train.loop import TrainConfig


class ChArUcoNetTask:
    higher_is_better = True
    metric_names = ("score", "corner_accuracy", "val_loss", "negative_detections")

    def __init__(self, config: TrainConfig, augmentation: AugmentConfig | None = AugmentConfig()):
        if config.label_sigma != TrainConfig.label_sigma:
            raise DeepCharucoError("--label-sigma applies to RefineNet's targets; ChArUcoNet's are cell classes")
        if config.width == "fast" or config.teacher:
            raise DeepCharucoError("--width fast and --teacher train RefineNet here; a fast ChArUcoNet is distilled "
                                   "from a teacher by python -m train.distill --arch fast")
        if (config.distill_weight, config.temperature) != (TrainConfig.distill_weight, TrainConfig.temperature):
            raise DeepCharucoError("--distill-weight and --temperature apply to RefineNet's --teacher")
        if augmentation is not None and config.crop:
            augmentation = replace(augmentation, crop=parse_crop(config.crop))
        if augmentation is not None and config.shadow_edges:
            augmentation = replace(augmentation, shadow_edge_p=config.shadow_edges)
        if config.heads not in HEADS:
            raise DeepCharucoError(f"--heads {config.heads!r}: choose one of {', '.join(HEADS)}")
        self.points_only = config.heads == "points"
        if self.points_only:
            self.metric_names = POINT_METRICS
            if config.id_positive_weight != TrainConfig.id_positive_weight:
                raise DeepCharucoError("--id-positive-weight weights the ID loss, which --heads points leaves out")
        train_paths, val_paths = split_shards(config.data, config.val_fraction)
        reader = ShardReader(train_paths[0])
        if not self.points_only and not reader.single_board:
            raise DeepCharucoError(f"{config.data} holds renders of random boards (datagen.render --family): an ID "
                                   "head learns one board's corners; train the point head alone with --heads points, "
                                   "or render one board with datagen.render --board B.yaml")
        self.board, self.image_size = reader.board_of(0), reader.image_size
        if self.points_only and config.init:
            # The ID head is carried along untrained; its size (and the board stored with it, which a
            # Detector without board= looks for) is the warm start's, so that every layer loads.
            self.board = BoardSpec.from_dict(read_checkpoint(config.init, "charuconet")["board"])
        crop = augmentation.crop if augmentation is not None else None
        if crop and (crop[0] > self.image_size[0] or crop[1] > self.image_size[1]):
            raise DeepCharucoError(f"--crop {crop[0]}x{crop[1]} is larger than the {self.image_size[0]}x{self.image_size[1]} "
                                   f"frames in {config.data}: choose a smaller crop")
        architecture = (ChArUcoNetConfig.lite if config.width == "lite" else ChArUcoNetConfig.paper)(self.board.num_corners)
        torch.manual_seed(config.seed)
        self.model = ChArUcoNet(architecture)
        self.id_weights = torch.full((self.board.num_corners + 1,), float(config.id_positive_weight))
        self.id_weights[-1] = 1.0  # the dustbin
        shard_board = None if self.points_only else self.board
        self.train_set = FrameDataset(train_paths, shard_board, augmentation, seed=config.seed)
        self.val_set = FrameDataset(val_paths, shard_board, augmentation=None)

    def loss(self, model, batch: dict, device: torch.device) -> torch.Tensor:
        points, ids = model(batch["image"].to(device, non_blocking=True))
        point_loss = F.cross_entropy(points.float(), batch["points"].to(device))
        if self.points_only:
            return point_loss
        return point_loss + F.cross_entropy(ids.float(), batch["ids"].to(device), weight=self.id_weights.to(device))

    def validate(self, model, batches: list[dict], device: torch.device) -> dict:
        if self.points_only:
            return validate_points(model, batches, device)
        accuracies, false_positives, losses = [], [], []
        for batch in batches:
            points, ids = model(batch["image"].to(device))
            losses.append(float(F.cross_entropy(points.float(), batch["points"].to(device))
                                + F.cross_entropy(ids.float(), batch["ids"].to(device))))
            for k in range(len(points)):
                found_ids, pixels, scores = decode_cells(points[k].cpu(), ids[k].cpu())
                if batch["has_board"][k]:
                    detection = Detection(found_ids, pixels, scores)
                    accuracies.append(match_corners(detection, batch["corners"][k].numpy(), batch["visible"][k].numpy()).accuracy)
                else:
                    false_positives.append(len(found_ids))
        accuracy = float(np.mean(accuracies)) if accuracies else 0.0
        return {"score": accuracy, "corner_accuracy": accuracy, "val_loss": float(np.mean(losses)),
                "negative_detections": float(np.mean(false_positives)) if false_positives else 0.0}

    def checkpoint_kwargs(self) -> dict:
        return {"board": self.board, "input_size": self.image_size, **({"heads": "points"} if self.points_only else {})}


POINT_METRICS = ("score", "point_f1", "point_recall", "point_precision", "val_loss", "negative_detections")
POINT_CONFIDENCE = 0.5  # validation's operating point for the point head (the Detector's own is chosen later)
POINT_TOLERANCE_PX = 3.0  # the paper's corner-accuracy distance


def match_points(found: np.ndarray, truth: np.ndarray) -> int:
    """How many of the (M, 2) ``found`` pixels lie within 3 px of a distinct (T, 2) ``truth`` corner
    (greedy by distance: each truth corner takes at most one)."""
    if len(found) == 0 or len(truth) == 0:
        return 0
    distance = np.linalg.norm(found[:, None].astype(np.float64) - truth[None], axis=2)
    matched, used_found, used_truth = 0, set(), set()
    for flat in np.argsort(distance, axis=None):
        i, j = divmod(int(flat), distance.shape[1])
        if distance[i, j] > POINT_TOLERANCE_PX:
            break
        if i not in used_found and j not in used_truth:
            used_found.add(i)
            used_truth.add(j)
            matched += 1
    return matched


def validate_points(model, batches: list[dict], device: torch.device) -> dict:
    """The point head alone on validation frames of any boards: F1 (score), recall and precision of its corners
    (cells at confidence >= 0.5, within 3 px of a visible true corner), corners on negatives, point loss."""
    found_total = true_total = matched_total = 0
    false_positives, losses = [], []
    for batch in batches:
        points, _ = model(batch["image"].to(device))
        losses.append(float(F.cross_entropy(points.float(), batch["points"].to(device))))
        for k in range(len(points)):
            _, pixels, _ = point_candidates(points[k].cpu(), POINT_CONFIDENCE)
            if not batch["has_board"][k]:
                false_positives.append(len(pixels))
                found_total += len(pixels)
                continue
            visible = batch["visible"][k].numpy()
            truth = batch["corners"][k].numpy()[visible]
            truth = truth[np.isfinite(truth).all(axis=1)]
            found_total += len(pixels)
            true_total += len(truth)
            matched_total += match_points(pixels, truth)
    recall = matched_total / true_total if true_total else 0.0
    precision = matched_total / found_total if found_total else 0.0
    f1 = 2 * recall * precision / (recall + precision) if recall + precision else 0.0
    return {"score": f1, "point_f1": f1, "point_recall": recall, "point_precision": precision,
            "val_loss": float(np.mean(losses)),
            "negative_detections": float(np.mean(false_positives)) if false_positives else 0.0}


def main(argv: list[str] | None = None) -> int:
    return run_trainer("charuconet", ChArUcoNetTask, __doc__, "score (corner accuracy; --heads points: point F1)",
                       {"data": "data/renders", "out": "runs/charuconet"}, argv)

if __name__ == "__main__":
    sys.exit(main())
