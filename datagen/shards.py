"""HDF5 frame shards (DESIGN.md "HDF5 shard schema"): `write_shard`, `ShardReader`, `index.json`.

A shard appears under its final name only when complete: it is written to a hidden
temporary name in the same folder and renamed, which is atomic on POSIX file systems. So the
set of ``shard-*.h5`` files *is* the set of complete shards, whatever was killed when; the
``index.json`` beside them is rebuilt from those files after every write and serves as a
summary for people and tools, never as the source of truth.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import h5py
import numpy as np

from deepcharuco.board import BoardSpec

SCHEMA_VERSION = 1
INDEX_NAME = "index.json"
_SHARD_RE = re.compile(r"^shard-(\d{5,})\.h5$")


class ShardError(ValueError):
    """A shard or shard folder that does not follow the schema."""


def shard_name(index: int) -> str:
    return f"shard-{index:05d}.h5"


@dataclass
class FrameLabels:
    """One rendered frame and its labels, as stored in a shard.

    Attributes:
        image: (H, W) uint8.
        corners: (C, 2) float32 true sub-pixel corner positions, NaN where not projected.
        visible: (C,) bool, inside the image and not occluded.
        K: (3, 3) intrinsics; rvec, tvec: (3,) board -> camera pose (zeros for negatives).
        meta: per-frame scalars (seed, lux, exposure_s, gain, blur_px, has_board, tags ...).
    """

    image: np.ndarray
    corners: np.ndarray
    visible: np.ndarray
    K: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    meta: dict = field(default_factory=dict)


def _check_frames(frames: list[FrameLabels], board: BoardSpec) -> tuple[int, int]:
    if not frames:
        raise ShardError("a shard needs at least one frame")
    height, width = frames[0].image.shape
    keys = set(frames[0].meta)
    if "has_board" not in keys:
        raise ShardError("meta must hold has_board (False for negative frames)")
    for i, frame in enumerate(frames):
        if frame.image.dtype != np.uint8 or frame.image.shape != (height, width):
            raise ShardError(f"frame {i}: image must be uint8 {(height, width)}, got {frame.image.dtype} {frame.image.shape}")
        if frame.corners.shape != (board.num_corners, 2) or frame.visible.shape != (board.num_corners,):
            raise ShardError(
                f"frame {i}: corners/visible must be ({board.num_corners}, 2)/({board.num_corners},) for this board, "
                f"got {frame.corners.shape}/{frame.visible.shape}"
            )
        if set(frame.meta) != keys:
            raise ShardError(f"frame {i}: meta keys {sorted(frame.meta)} differ from frame 0's {sorted(keys)}")
        if not frame.meta["has_board"] and (np.any(np.isfinite(frame.corners)) or np.any(frame.visible)):
            raise ShardError(f"frame {i} is a negative (has_board False) but carries corners")
    return width, height


def write_shard(
    directory: str | Path, index: int, frames: list[FrameLabels], board: BoardSpec, generator: dict,
    created: str | None = None,
) -> Path:
    """Write ``frames`` as shard ``index`` in ``directory`` atomically, then refresh index.json.

    ``generator`` (package version, command-line arguments ...) is stored as JSON; ``created``
    defaults to now (UTC, ISO 8601). Everything else in the file is a function of the inputs.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    width, height = _check_frames(frames, board)
    final = directory / shard_name(index)
    temporary = directory / f".{final.name}.tmp-{os.getpid()}"
    n = len(frames)
    try:
        with h5py.File(temporary, "w", track_order=True) as f:
            f.attrs["schema_version"] = SCHEMA_VERSION
            f.attrs["board"] = board.to_json()
            f.attrs["generator"] = json.dumps(generator, sort_keys=True)
            f.attrs["image_size"] = np.array([width, height], dtype=np.int64)
            f.attrs["created"] = created or datetime.now(timezone.utc).isoformat(timespec="seconds")
            f.create_dataset("images", data=np.stack([fr.image for fr in frames]), chunks=(1, height, width),
                             compression="gzip", compression_opts=4, shuffle=True, track_times=False)
            for name, dtype, stack in [
                ("corners", np.float32, [fr.corners for fr in frames]),
                ("visible", bool, [fr.visible for fr in frames]),
                ("K", np.float32, [fr.K for fr in frames]),
                ("rvec", np.float32, [np.ravel(fr.rvec) for fr in frames]),
                ("tvec", np.float32, [np.ravel(fr.tvec) for fr in frames]),
            ]:
                f.create_dataset(name, data=np.stack(stack).astype(dtype), track_times=False)
            meta = f.create_group("meta", track_order=True)
            for key in frames[0].meta:
                values = [fr.meta[key] for fr in frames]
                data = (np.array(values, dtype=h5py.string_dtype()) if isinstance(values[0], str)
                        else np.asarray(values))
                if data.shape != (n,):
                    raise ShardError(f"meta {key!r} must be one scalar per frame")
                meta.create_dataset(key, data=data, track_times=False)
        os.replace(temporary, final)
    finally:
        temporary.unlink(missing_ok=True)
    update_index(directory)
    return final


def list_shards(directory: str | Path) -> list[Path]:
    """Complete shards in ``directory``, in index order (read from the files, not index.json)."""
    directory = Path(directory)
    if not directory.is_dir():
        raise ShardError(f"{directory} is not a folder of shards (render some with python -m datagen.render)")
    return sorted((p for p in directory.iterdir() if _SHARD_RE.match(p.name)), key=lambda p: int(_SHARD_RE.match(p.name)[1]))


def update_index(directory: str | Path) -> dict:
    """Rebuild ``index.json`` from the complete shards on disk; returns its content."""
    directory = Path(directory)
    shards = []
    for path in list_shards(directory):
        with h5py.File(path, "r") as f:
            shards.append({"file": path.name, "frames": int(f["images"].shape[0])})
    index = {"schema_version": SCHEMA_VERSION, "frames": sum(s["frames"] for s in shards), "shards": shards}
    temporary = directory / f".{INDEX_NAME}.tmp-{os.getpid()}"
    temporary.write_text(json.dumps(index, indent=1) + "\n")
    os.replace(temporary, directory / INDEX_NAME)
    return index


class ShardReader:
    """Random access to one shard's frames; the file opens on first use (so it can be handed
    to DataLoader worker processes unopened) and stays open."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.is_file():
            raise ShardError(f"shard {self.path} does not exist")
        with h5py.File(self.path, "r") as f:
            version = int(f.attrs.get("schema_version", -1))
            if version != SCHEMA_VERSION:
                raise ShardError(f"{self.path} has schema_version {version}, this code reads {SCHEMA_VERSION}: re-render it")
            self.board = BoardSpec.from_json(f.attrs["board"])
            self.generator = json.loads(f.attrs["generator"])
            self.image_size = tuple(int(v) for v in f.attrs["image_size"])
            self.meta_keys = list(f["meta"].keys())
            self._length = int(f["images"].shape[0])
        self._file: h5py.File | None = None

    def __len__(self) -> int:
        return self._length

    def _handle(self) -> h5py.File:
        if self._file is None:
            self._file = h5py.File(self.path, "r")
        return self._file

    def __getitem__(self, i: int) -> FrameLabels:
        if not -self._length <= i < self._length:
            raise IndexError(f"frame {i} out of range for {self._length} frames in {self.path.name}")
        f = self._handle()
        meta = {}
        for key in self.meta_keys:
            value = f["meta"][key][i]
            meta[key] = value.decode() if isinstance(value, bytes) else value.item()
        return FrameLabels(image=f["images"][i], corners=f["corners"][i], visible=f["visible"][i],
                           K=f["K"][i], rvec=f["rvec"][i], tvec=f["tvec"][i], meta=meta)

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_file": None}  # h5py handles do not cross processes
