"""Test frames from shard folders (renders, rendered sequences, auto-labelled captures) and the choice of
the synthetic protocols' well-lit images."""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from pathlib import Path

import numpy as np

from datagen.shards import ShardReader, list_shards
from deepcharuco.boards.board import BoardSpec
from deepcharuco.core.errors import DeepCharucoError
from evaluate.paper.protocols import TestFrame

WELL_LIT_LUX = 100.0  # the paper's "good lighting" (its normal-light videos are 3..700 lux)
STATIC_BLUR_PX = 0.5  # "random static pose, minimum motion blur"
FINGERPRINT_CHARS = 16  # hex digits of a test set's sha256 shown: 64 bits tell sets apart


class TestSetError(DeepCharucoError):
    """A test set that cannot be evaluated as asked."""

    __test__ = False  # not a pytest class, despite the name


def load_frames(directory: str | Path, board: BoardSpec | None = None, limit: int | None = None,
                positives_only: bool = True) -> list[TestFrame]:
    """Frames of every shard in ``directory`` (shard order, then frame order), as `TestFrame`s.

    ``board``: when given, shards of another board are refused (their corner IDs mean something else).
    ``limit``: at most this many frames. Negatives (has_board False) are skipped unless asked for."""
    directory = Path(directory)
    paths = list_shards(directory) if directory.is_dir() else []
    if not paths:
        raise TestSetError(f"no shard-*.h5 files in {directory}: render a test set with python -m datagen.render "
                           f"--seed 1000 --out {directory} (or python -m evaluate.paper.sequences --out {directory})")
    frames: list[TestFrame] = []
    for path in paths:
        reader = ShardReader(path)
        if board is not None and reader.board != board:
            raise TestSetError(f"{path} holds frames of {reader.board}, not of {board}: evaluate it with that board")
        for i in range(len(reader)):
            labels = reader[i]
            has_board = bool(labels.meta.get("has_board", True))
            if positives_only and not has_board:
                continue
            truth = has_board and np.all(np.isfinite(labels.tvec)) and np.any(labels.tvec != 0)
            frames.append(TestFrame(
                image=labels.image, corners=labels.corners.astype(np.float32), visible=labels.visible.astype(bool),
                K=labels.K.astype(np.float64), rvec=labels.rvec.astype(np.float64) if truth else None,
                tvec=labels.tvec.astype(np.float64) if truth else None, name=f"{path.name}#{i}", meta=labels.meta))
            if limit is not None and len(frames) >= limit:
                reader.close()
                return frames
        reader.close()
    return frames


def frames_fingerprint(frames: list[TestFrame]) -> str:
    """A short sha256 over the frames' images and corner labels, in order: which pixels a table was measured
    on. A test set re-rendered from the same seed gives the same fingerprint on one machine; on another CPU
    Cycles may give other pixels, and the fingerprint says so where the numbers alone would not."""
    digest = hashlib.sha256()
    for frame in frames:
        digest.update(np.ascontiguousarray(frame.image).tobytes())
        digest.update(np.ascontiguousarray(frame.corners, np.float32).tobytes())
    return digest.hexdigest()[:FINGERPRINT_CHARS]


def board_of(directory: str | Path) -> BoardSpec:
    """The board the first shard in ``directory`` was made for."""
    paths = list_shards(directory) if Path(directory).is_dir() else []
    if not paths:
        raise TestSetError(f"no shard-*.h5 files in {directory}")
    return ShardReader(paths[0]).board


def group_by_sequence(frames: list[TestFrame]) -> "OrderedDict[str, list[TestFrame]]":
    """Frames grouped by their ``meta["sequence"]`` (rendered sequences, auto-labelled videos), in order."""
    groups: OrderedDict[str, list[TestFrame]] = OrderedDict()
    for frame in frames:
        name = frame.meta.get("sequence")
        if name is not None:
            groups.setdefault(str(name), []).append(frame)
    return groups


def is_well_lit(frame: TestFrame, min_lux: float = WELL_LIT_LUX, max_blur_px: float = STATIC_BLUR_PX) -> bool:
    """Good light, no motion blur, every board corner in view: the paper's starting images."""
    meta = frame.meta
    return (bool(meta.get("has_board", True)) and bool(frame.visible.all())
            and float(meta.get("lux", min_lux)) >= min_lux and float(meta.get("blur_px", 0.0)) <= max_blur_px)


def select_well_lit(frames: list[TestFrame], count: int = 20, seed: int = 0) -> list[TestFrame]:
    """``count`` well-lit frames with different static poses, chosen with ``seed``.

    At most one frame per sequence (a sequence's frames share one pose) and per distinct scene
    otherwise; fewer than ``count`` candidates is an error that says where to get more."""
    candidates: OrderedDict[str, TestFrame] = OrderedDict()
    for frame in frames:
        if is_well_lit(frame):
            key = str(frame.meta.get("sequence", frame.name))
            candidates.setdefault(key, frame)
    if len(candidates) < count:
        raise TestSetError(f"only {len(candidates)} well-lit frames with the whole board in view "
                           f"(lux >= {WELL_LIT_LUX:g}, blur <= {STATIC_BLUR_PX} px, all corners visible) where "
                           f"{count} are needed: render more test frames or lower --synthetic-images")
    chosen = np.random.default_rng(seed).permutation(len(candidates))[:count]
    pool = list(candidates.values())
    return [pool[i] for i in sorted(chosen)]
