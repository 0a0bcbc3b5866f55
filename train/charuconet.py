"""Train ChArUcoNet on rendered shards: ``python -m train.charuconet --data data/renders --out runs/charuconet``.

Loss: cross-entropy on the 65-way point labels plus on the (N+1)-way ID labels of every 8x8
cell; ``--id-positive-weight w`` weights the cells holding a corner w times in the ID term
(the point head learns "corner here" within a few hundred steps, while the ID head, whose
corner cells are ~2 % of all cells, stayed near chance for thousands of steps on a CPU run).
Validation: the paper's corner accuracy (right ID within 3 px, / N corners) on the validation
shards' positives, detections on negatives, and the loss.
"""

from __future__ import annotations

import sys
from dataclasses import replace

import numpy as np
import torch
import torch.nn.functional as F

from datagen.shards import ShardReader
from deepcharuco.detection import Detection
from deepcharuco.errors import DeepCharucoError
from deepcharuco.metrics import match_corners
from deepcharuco.models.cells import decode_cells
from deepcharuco.models.charuconet import ChArUcoNet, ChArUcoNetConfig
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
        if augmentation is not None and config.crop:
            augmentation = replace(augmentation, crop=parse_crop(config.crop))
        train_paths, val_paths = split_shards(config.data, config.val_fraction)
        reader = ShardReader(train_paths[0])
        self.board, self.image_size = reader.board, reader.image_size
        crop = augmentation.crop if augmentation is not None else None
        if crop and (crop[0] > self.image_size[0] or crop[1] > self.image_size[1]):
            raise DeepCharucoError(f"--crop {crop[0]}x{crop[1]} is larger than the {self.image_size[0]}x{self.image_size[1]} "
                                   f"frames in {config.data}: choose a smaller crop")
        architecture = (ChArUcoNetConfig.lite if config.width == "lite" else ChArUcoNetConfig.paper)(self.board.num_corners)
        torch.manual_seed(config.seed)
        self.model = ChArUcoNet(architecture)
        self.id_weights = torch.full((self.board.num_corners + 1,), float(config.id_positive_weight))
        self.id_weights[-1] = 1.0  # the dustbin
        self.train_set = FrameDataset(train_paths, self.board, augmentation, seed=config.seed)
        self.val_set = FrameDataset(val_paths, self.board, augmentation=None)

    def loss(self, model, batch: dict, device: torch.device) -> torch.Tensor:
        points, ids = model(batch["image"].to(device, non_blocking=True))
        return (F.cross_entropy(points.float(), batch["points"].to(device))
                + F.cross_entropy(ids.float(), batch["ids"].to(device), weight=self.id_weights.to(device)))

    def validate(self, model, batches: list[dict], device: torch.device) -> dict:
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
        return {"board": self.board, "input_size": self.image_size}


def main(argv: list[str] | None = None) -> int:
    return run_trainer("charuconet", ChArUcoNetTask, __doc__, "corner accuracy",
                       {"data": "data/renders", "out": "runs/charuconet"}, argv)

if __name__ == "__main__":
    sys.exit(main())
