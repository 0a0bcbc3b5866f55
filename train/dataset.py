"""Torch datasets over HDF5 frame shards, with ChArUcoNet targets.

Shards are opened lazily in each DataLoader worker (`datagen.shards.ShardReader` pickles
unopened) and read a frame at a time; nothing is loaded whole. Train and validation are split
by shard. Augmentation draws come from ``default_rng([seed, epoch, index])``, so an epoch's
samples are a pure function of (seed, epoch) — what makes resuming exact.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from datagen.shards import ShardError, ShardReader, list_shards
from deepcharuco.boards.board import BoardSpec
from deepcharuco.networks.cells import encode_cells
from deepcharuco.networks.charuconet import CELL
from train.augment import AugmentConfig, augment


def split_shards(directory: str | Path, val_fraction: float = 0.1,
                 make_them: str = "render some with python -m datagen.render") -> tuple[list[Path], list[Path]]:
    """(train, validation) shard paths: every k-th shard validates, k = round(1 / val_fraction).
    With a single shard, it serves both (a tiny run still gets a validation number).
    ``make_them`` completes the error message of an empty folder."""
    paths = list_shards(directory)
    if not paths:
        raise ShardError(f"{directory} holds no shards ({make_them})")
    if len(paths) == 1 or val_fraction <= 0:
        return paths, paths[:1]
    step = max(2, round(1.0 / val_fraction))
    validation = paths[step - 1::step] or paths[-1:]
    return [p for p in paths if p not in validation], validation


class FrameDataset(torch.utils.data.Dataset):
    """Frames of the given shards -> dict(image (1, H, W) float32 in [0, 1], points (H/8, W/8) int64,
    ids (H/8, W/8) int64, corners (C, 2) float32, visible (C,) bool, has_board bool).

    ``board=None`` takes shards of any boards (shards of other boards, or of random boards of a marker
    family, ``datagen.render --family``; for the point head alone): C is then the largest board's corner
    count, smaller boards' rows padded with NaN and not visible (a batch stacks), and ``ids`` are each
    frame's own board's corner IDs, which mean nothing across boards. A frame of an inverted print is given as
    the detector sees it, negated about its brightest level after augmentation (`print_face.canonical_view`)."""

    def __init__(self, shards: list[Path], board: BoardSpec | None, augmentation: AugmentConfig | None = AugmentConfig(),
                 seed: int = 0):
        self.readers = [ShardReader(p) for p in shards]
        self.num_corners = max(r.max_corners for r in self.readers) if board is None else board.num_corners
        for reader in self.readers:
            if board is not None and reader.board != board:
                raise ShardError(f"{reader.path} was rendered for {reader.board}, not for {board}")
            width, height = reader.image_size
            if width % CELL or height % CELL:
                raise ShardError(f"{reader.path}: frames of {width}x{height} are not multiples of {CELL}")
        self.starts = np.cumsum([0] + [len(r) for r in self.readers])
        self.augmentation = augmentation
        self.seed = seed
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return int(self.starts[-1])

    def __getitem__(self, index: int) -> dict:
        shard = int(np.searchsorted(self.starts, index, side="right") - 1)
        frame = self.readers[shard][int(index - self.starts[shard])]
        image = frame.image.astype(np.float32) / 255.0
        corners, visible = frame.corners.astype(np.float32), frame.visible.astype(bool)
        if len(corners) < self.num_corners:  # a smaller board among a family's (board=None)
            missing = self.num_corners - len(corners)
            corners = np.concatenate([corners, np.full((missing, 2), np.nan, np.float32)])
            visible = np.concatenate([visible, np.zeros(missing, bool)])
        has_board = bool(frame.meta["has_board"])
        if self.augmentation is not None:
            rng = np.random.default_rng([self.seed, self.epoch, index])
            image, corners, visible = augment(image, corners, visible, has_board, rng, self.augmentation)
        if frame.board is not None and frame.board.inverted:
            # What the runtime's networks see (`print_face.canonical_view`): the camera's image, shadows and noise
            # included, negated about its own white. Not flipped for a mirrored face: an X-junction is one either way.
            image = image.max() - image
        points, ids = encode_cells(corners, visible, *image.shape)
        return {"image": torch.from_numpy(np.ascontiguousarray(image))[None], "points": torch.from_numpy(points),
                "ids": torch.from_numpy(ids), "corners": torch.from_numpy(corners), "visible": torch.from_numpy(visible),
                "has_board": has_board}
