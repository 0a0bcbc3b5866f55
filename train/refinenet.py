"""Train RefineNet on corner patches: ``python -m train.refinenet --data data/patches --out runs/refinenet``.

Loss: 4096-way cross-entropy against a Gaussian around the true offset on the 64x64 grid
(``--label-sigma`` cells of 1/8 px; 0 = the paper's one-hot cell). The one-hot target gives a
wrong-by-a-pixel guess the same loss as a wild one, and here the networks sat at the uniform
distribution's loss (ln 4096) for the first thousand steps; the Gaussian's gradient points
towards the corner from the start. Validation: mean distance (px) between the decoded offset
(argmax + soft-argmax) and the truth, and its 90th percentile.

``--teacher`` distils another RefineNet into this one (e.g. ``--width fast`` from the shipped lite one, on patches
of drawn frames, ``python -m train.drawn_patches``): the loss adds ``--distill-weight`` times T^2 KL(teacher ||
student) of the 4096-way softmax at temperature T (``--temperature``), and validation reports the teacher's own
errors on the same patches (``teacher_error_px``, ``teacher_p90_px``: the mark to reach).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from datagen.shards import read_patch_shard
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.networks.checkpoint import load_refinenet
from deepcharuco.networks.refinenet import CENTRE_LOW, GRID, RefineNet, RefineNetConfig, decode_offsets, offset_to_cell
from train.cli import run_trainer
from train.dataset import split_shards
from train.loop import TrainConfig


class PatchDataset(torch.utils.data.Dataset):
    """All patches of the given patch shards (small: read whole) -> dict(image (1, 24, 24), target, offset)."""

    def __init__(self, shards: list[Path]):
        parts = [read_patch_shard(p) for p in shards]
        self.patches = np.concatenate([p for p, _, _ in parts])
        self.offsets = np.concatenate([o for _, o, _ in parts]).astype(np.float32)

    def __len__(self) -> int:
        return len(self.patches)

    def __getitem__(self, index: int) -> dict:
        offset = torch.from_numpy(self.offsets[index])
        return {"image": torch.from_numpy(self.patches[index].astype(np.float32) / 255.0)[None],
                "target": offset_to_cell(offset), "offset": offset}


def gaussian_targets(offsets: torch.Tensor, sigma: float) -> torch.Tensor:
    """(B, 2) offsets (x, y) in patch pixels -> (B, 4096) target distributions: a separable Gaussian of
    ``sigma`` grid cells about the offset's place on the 64x64 grid, row-major like the logits."""
    place = (offsets - CENTRE_LOW) * (GRID // 8) - 0.5  # continuous grid coordinates of the cell centres
    steps = torch.arange(GRID, device=offsets.device, dtype=torch.float32)
    along = torch.softmax(-0.5 * ((steps[None, None, :] - place[:, :, None]) / sigma) ** 2, dim=2)  # (B, 2, 64)
    return (along[:, 1, :, None] * along[:, 0, None, :]).flatten(1)


class RefineNetTask:
    higher_is_better = False

    def __init__(self, config: TrainConfig):
        if config.crop:
            raise DeepCharucoError("--crop applies to ChArUcoNet's frames; RefineNet trains on whole 24x24 patches")
        if config.shadow_edges:
            raise DeepCharucoError("--shadow-edges applies to ChArUcoNet's crops; RefineNet's patches get shadow edges "
                                   "when they are made: python -m datagen.patches --shadow-edges P")
        if config.heads != TrainConfig.heads:
            raise DeepCharucoError("--heads chooses ChArUcoNet's heads; RefineNet has one")
        if config.id_positive_weight != 1.0:
            raise DeepCharucoError("--id-positive-weight applies to ChArUcoNet's ID head; RefineNet has none")
        training, validation = split_shards(config.data, config.val_fraction,
                                            "make some with python -m datagen.patches")
        torch.manual_seed(config.seed)
        self.model = RefineNet(getattr(RefineNetConfig, config.width)())
        self.train_set, self.val_set = PatchDataset(training), PatchDataset(validation)
        self.label_sigma = config.label_sigma
        self.teacher = load_refinenet(config.teacher)[0].requires_grad_(False) if config.teacher else None
        self.distill_weight, self.temperature = config.distill_weight, config.temperature
        self.metric_names = ("score", "mean_error_px", "p90_error_px") + \
            (("teacher_error_px", "teacher_p90_px") if self.teacher is not None else ())

    def loss(self, model, batch: dict, device: torch.device) -> torch.Tensor:
        image = batch["image"].to(device)
        logits = model(image).float()
        if self.label_sigma <= 0:
            loss = F.cross_entropy(logits, batch["target"].to(device))
        else:
            target = gaussian_targets(batch["offset"].to(device), self.label_sigma)
            loss = -(target * F.log_softmax(logits, dim=1)).sum(dim=1).mean()
        if self.teacher is None or self.distill_weight == 0:
            return loss
        with torch.no_grad():
            taught = F.softmax(self.teacher.to(device)(image).float() / self.temperature, dim=1)
        kl = F.kl_div(F.log_softmax(logits / self.temperature, dim=1), taught, reduction="batchmean")
        return loss + self.distill_weight * self.temperature ** 2 * kl

    def validate(self, model, batches: list[dict], device: torch.device) -> dict:
        error = _errors(model, batches, device)
        metrics = {"score": float(error.mean()), "mean_error_px": float(error.mean()),
                   "p90_error_px": float(torch.quantile(error, 0.9))}
        if self.teacher is not None:
            taught = _errors(self.teacher.to(device), batches, device)
            metrics.update(teacher_error_px=float(taught.mean()), teacher_p90_px=float(torch.quantile(taught, 0.9)))
        return metrics

    def checkpoint_kwargs(self) -> dict:
        return {}


def _errors(model, batches: list[dict], device: torch.device) -> torch.Tensor:
    """(N,) distances (px) between ``model``'s decoded offsets and the labels over ``batches``."""
    with torch.no_grad():
        return torch.cat([torch.linalg.norm(decode_offsets(model(b["image"].to(device)).float()).cpu() - b["offset"],
                                            dim=1) for b in batches])


def main(argv: list[str] | None = None) -> int:
    return run_trainer("refinenet", RefineNetTask, __doc__, "mean error (px)",
                       {"data": "data/patches", "out": "runs/refinenet", "batch_size": 256}, argv)

if __name__ == "__main__":
    sys.exit(main())
