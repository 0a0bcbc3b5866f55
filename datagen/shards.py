"""HDF5 frame shards (docs/conventions.md "HDF5 shard schema"): `write_shard`, `ShardReader`, `index.json`.

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
from contextlib import contextmanager
import socket
from dataclasses import dataclass, field
from datetime import datetime, timezone
from functools import lru_cache
from pathlib import Path

import h5py
import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.core.errors import DeepCharucoError

SCHEMA_VERSION = 1
INDEX_NAME = "index.json"
_SHARD_RE = re.compile(r"^shard-(\d{5,})\.h5$")


class ShardError(DeepCharucoError, ValueError):
    """A shard or shard folder that does not follow the schema."""


def shard_name(index: int) -> str:
    return f"shard-{index:05d}.h5"


def temporary_prefix(index: int) -> str:
    """Shard ``index`` is written as ``<prefix><host>-<pid>`` until complete (unique across a cluster)."""
    return f".{shard_name(index)}.tmp-"


@contextmanager
def _atomic(final: Path, index: int):
    """Yields a temporary path beside ``final``, renamed to it only if the block completes."""
    temporary = final.parent / f"{temporary_prefix(index)}{socket.gethostname()}-{os.getpid()}"
    try:
        yield temporary
        os.replace(temporary, final)
    finally:
        temporary.unlink(missing_ok=True)


@contextmanager
def _hdf5_atomic(final: Path, index: int):
    """Yields a new HDF5 file built in memory; when the block completes, its bytes are written
    beside ``final`` under a temporary name and renamed to it (`_atomic`).

    In memory because HDF5 crashes the process (SIGSEGV on close) when a write to disk fails,
    as it does on a full disk; written by Python, a full disk is an ordinary OSError, the
    temporary file is removed and the caller can say what happened."""
    with _atomic(final, index) as temporary:
        f = h5py.File(temporary.name, "w", driver="core", backing_store=False, track_order=True)
        try:
            yield f
            f.flush()
            image = f.id.get_file_image()
        finally:
            f.close()
        with open(temporary, "wb") as out:
            out.write(image)


@dataclass
class MarkerLabels:
    """The markers of a frame's board (M = the board's markers, in `BoardSpec.marker_corners` order).

    Attributes:
        ids: (M,) int32 dictionary IDs.
        corners: (M, 4, 2) float32 image positions of each marker's corners in OpenCV's order (clockwise
            from the printed marker's top-left, as ``cv2.aruco`` detects them), NaN where not projected.
        centres: (M, 2) float32 image position of each marker's centre point (the projection of the
            centre, not the mean of the corners), NaN where not projected.
        visible: (M,) bool: all four corners and the centre inside the image and not occluded.
    """

    ids: np.ndarray
    corners: np.ndarray
    centres: np.ndarray
    visible: np.ndarray


@dataclass
class FrameLabels:
    """One rendered frame and its labels, as stored in a shard.

    Attributes:
        image: (H, W) uint8.
        corners: (C, 2) float32 true sub-pixel corner positions, NaN where not projected.
        visible: (C,) bool, inside the image and not occluded.
        K: (3, 3) intrinsics; rvec, tvec: (3,) board -> camera pose (zeros for negatives).
        meta: per-frame scalars (seed, lux, exposure_s, gain, blur_px, has_board, tags ...).
        board: the frame's board (C = its corners); read back from every shard (a shard of one board
            gives that board), needed when writing a shard of random boards (`write_shard` board=None).
        markers: marker labels, or None (shards written before they existed, or by writers without them).
        dist: (5,) float32 OpenCV distortion (k1 k2 p1 p2 k3) of the camera that took the frame, or None
            where the shard stores none (its frames are undistorted).
    """

    image: np.ndarray
    corners: np.ndarray
    visible: np.ndarray
    K: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    meta: dict = field(default_factory=dict)
    board: BoardSpec | None = None
    markers: MarkerLabels | None = None
    dist: np.ndarray | None = None


def _frame_boards(frames: list[FrameLabels], board: BoardSpec | None) -> list[BoardSpec]:
    """Each frame's board: ``board`` for a shard of one board (a frame naming another is refused), else
    every frame's own."""
    boards = []
    for i, frame in enumerate(frames):
        if board is None and frame.board is None:
            raise ShardError(f"frame {i} has no board: a shard of random boards (board=None) needs FrameLabels.board")
        if board is not None and frame.board is not None and frame.board != board:
            raise ShardError(f"frame {i} shows {frame.board}, not the shard's board {board}")
        boards.append(board if board is not None else frame.board)
    return boards


def _check_frames(frames: list[FrameLabels], boards: list[BoardSpec]) -> tuple[int, int]:
    if not frames:
        raise ShardError("a shard needs at least one frame")
    height, width = frames[0].image.shape
    keys = set(frames[0].meta)
    if "has_board" not in keys:
        raise ShardError("meta must hold has_board (False for negative frames)")
    with_markers = frames[0].markers is not None
    with_dist = frames[0].dist is not None
    for i, (frame, board) in enumerate(zip(frames, boards)):
        if frame.image.dtype != np.uint8 or frame.image.shape != (height, width):
            raise ShardError(f"frame {i}: image must be uint8 {(height, width)}, got {frame.image.dtype} {frame.image.shape}")
        if frame.corners.shape != (board.num_corners, 2) or frame.visible.shape != (board.num_corners,):
            raise ShardError(
                f"frame {i}: corners/visible must be ({board.num_corners}, 2)/({board.num_corners},) for this board, "
                f"got {frame.corners.shape}/{frame.visible.shape}"
            )
        if (frame.markers is not None) != with_markers or (frame.dist is not None) != with_dist:
            raise ShardError(f"frame {i}: every frame of a shard has marker labels and dist, or none does")
        if frame.markers is not None:
            m = board.num_markers
            shapes = (frame.markers.ids.shape, frame.markers.corners.shape, frame.markers.centres.shape,
                      frame.markers.visible.shape)
            if shapes != ((m,), (m, 4, 2), (m, 2), (m,)):
                raise ShardError(f"frame {i}: marker ids/corners/centres/visible must be ({m},)/({m}, 4, 2)/({m}, 2)/"
                                 f"({m},) for its board, got {shapes}")
        if frame.dist is not None and np.ravel(frame.dist).shape != (5,):
            raise ShardError(f"frame {i}: dist must hold OpenCV's 5 coefficients k1 k2 p1 p2 k3, got {np.shape(frame.dist)}")
        if set(frame.meta) != keys:
            raise ShardError(f"frame {i}: meta keys {sorted(frame.meta)} differ from frame 0's {sorted(keys)}")
        if not frame.meta["has_board"] and (np.any(np.isfinite(frame.corners)) or np.any(frame.visible)):
            raise ShardError(f"frame {i} is a negative (has_board False) but carries corners")
    return width, height


def _padded(arrays: list[np.ndarray], fill, dtype) -> np.ndarray:
    """(N, L, ...) stack of (l_i, ...) arrays, each padded with ``fill`` to L = max l_i."""
    length = max(len(a) for a in arrays)
    out = np.full((len(arrays), length, *np.shape(arrays[0])[1:]), fill, dtype=dtype)
    for i, array in enumerate(arrays):
        out[i, : len(array)] = array
    return out


def write_shard(
    directory: str | Path, index: int, frames: list[FrameLabels], board: BoardSpec | None, generator: dict,
    created: str | None = None, family: dict | None = None,
) -> Path:
    """Write ``frames`` as shard ``index`` in ``directory`` atomically, then refresh index.json.

    ``board``: the board every frame shows; None for frames of random boards (each frame's
    ``FrameLabels.board``), stored per frame with padded label arrays (docs/conventions.md) and
    ``family`` (how the boards were drawn) as the ``family`` attribute. ``generator`` (package
    version, command-line arguments ...) is stored as JSON; ``created`` defaults to
    `creation_time()`. Everything else in the file is a function of the inputs.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    boards = _frame_boards(frames, board)
    width, height = _check_frames(frames, boards)
    final = directory / shard_name(index)
    n = len(frames)
    data = {}  # name -> array, compressed when it is a padded (per-board) array
    if board is None:
        data["corners"] = _padded([fr.corners for fr in frames], np.nan, np.float32)
        data["visible"] = _padded([fr.visible for fr in frames], False, bool)
    else:
        data["corners"] = np.stack([fr.corners for fr in frames]).astype(np.float32)
        data["visible"] = np.stack([fr.visible for fr in frames]).astype(bool)
    data["K"] = np.stack([fr.K for fr in frames]).astype(np.float32)
    data["rvec"] = np.stack([np.ravel(fr.rvec) for fr in frames]).astype(np.float32)
    data["tvec"] = np.stack([np.ravel(fr.tvec) for fr in frames]).astype(np.float32)
    if frames[0].dist is not None:
        data["dist"] = np.stack([np.ravel(fr.dist) for fr in frames]).astype(np.float32)
    if board is None:
        data["corner_count"] = np.array([b.num_corners for b in boards], np.int32)
        data["marker_count"] = np.array([b.num_markers for b in boards], np.int32)
    if frames[0].markers is not None:
        data["marker_ids"] = _padded([fr.markers.ids for fr in frames], -1, np.int32)
        data["marker_corners"] = _padded([fr.markers.corners for fr in frames], np.nan, np.float32)
        data["marker_centres"] = _padded([fr.markers.centres for fr in frames], np.nan, np.float32)
        data["marker_visible"] = _padded([fr.markers.visible for fr in frames], False, bool)
    with _hdf5_atomic(final, index) as f:
        f.attrs["schema_version"] = SCHEMA_VERSION
        if board is not None:
            f.attrs["board"] = board.to_json()
        else:
            f.attrs["family"] = json.dumps(family or {}, sort_keys=True)
        f.attrs["generator"] = json.dumps(generator, sort_keys=True)
        f.attrs["image_size"] = np.array([width, height], dtype=np.int64)
        f.attrs["created"] = created or creation_time()
        f.create_dataset("images", data=np.stack([fr.image for fr in frames]), chunks=(1, height, width),
                         compression="gzip", compression_opts=4, shuffle=True, track_times=False)
        if board is None:
            f.create_dataset("boards", data=np.array([b.to_json() for b in boards], dtype=h5py.string_dtype()),
                             track_times=False)
        for name, array in data.items():
            # The marker arrays are mostly padding for a large board (NaN, -1): gzip costs little there.
            big = array.ndim >= 2 and name not in ("K", "rvec", "tvec", "dist")
            f.create_dataset(name, data=array, track_times=False,
                             **({"compression": "gzip", "compression_opts": 4, "shuffle": True} if big and board is None else {}))
        meta = f.create_group("meta", track_order=True)
        for key in frames[0].meta:
            values = [fr.meta[key] for fr in frames]
            data = (np.array(values, dtype=h5py.string_dtype()) if isinstance(values[0], str)
                    else np.asarray(values))
            if data.shape != (n,):
                raise ShardError(f"meta {key!r} must be one scalar per frame")
            meta.create_dataset(key, data=data, track_times=False)
    update_index(directory)
    return final


def creation_time() -> str:
    """Now (UTC, ISO 8601), or SOURCE_DATE_EPOCH when set, so that re-running a seeded render
    can give byte-identical files (the reproducible-builds convention)."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    moment = datetime.fromtimestamp(int(epoch), timezone.utc) if epoch else datetime.now(timezone.utc)
    return moment.isoformat(timespec="seconds")


def list_shards(directory: str | Path) -> list[Path]:
    """Complete shards in ``directory``, in index order (read from the files, not index.json)."""
    directory = Path(directory)
    if not directory.is_dir():
        raise ShardError(f"{directory} is not a folder of shards (render some with python -m datagen.render)")
    return sorted((p for p in directory.iterdir() if _SHARD_RE.match(p.name)), key=lambda p: int(_SHARD_RE.match(p.name)[1]))


def index_temporary_name(host: str, pid: int) -> str:
    """The name `update_index` writes the index under before renaming it: the writer's host and process ID, so that
    a run can tell its own killed writer's leftover from another host's task writing at that moment."""
    return f".{INDEX_NAME}.tmp-{host}-{pid}"


def index_temporary_writer(name: str) -> tuple[str, int] | None:
    """(host, process ID) of an index temporary's writer (`index_temporary_name`), or None for another name."""
    host, _, pid = name.partition(".tmp-")[2].rpartition("-")
    return (host, int(pid)) if host and pid.isdigit() else None


def update_index(directory: str | Path) -> dict:
    """Rebuild ``index.json`` from the complete shards on disk; returns its content."""
    directory = Path(directory)
    shards = []
    for path in list_shards(directory):
        shards.append({"file": path.name, "frames": len(ShardReader(path))})
    index = {"schema_version": SCHEMA_VERSION, "frames": sum(s["frames"] for s in shards), "shards": shards}
    temporary = directory / index_temporary_name(socket.gethostname(), os.getpid())
    temporary.write_text(json.dumps(index, indent=1) + "\n")
    os.replace(temporary, directory / INDEX_NAME)
    return index


FRAME_SHARD_FIX = ("delete it and rerun the command that made its folder with --resume (python -m datagen.render "
                   "or evaluate.paper.sequences: it renders exactly the missing shards)")
PATCH_SHARD_FIX = "delete the folder and rerun python -m datagen.patches"


def _first_line(error: Exception) -> str:
    return (str(error).splitlines() or [type(error).__name__])[0]


@contextmanager
def _open(path: Path, fix: str):
    """``h5py.File(path, "r")``, with a `ShardError` naming the file and ``fix`` when it is not a
    readable HDF5 file (truncated by a full disk or an interrupted copy, or not HDF5 at all)."""
    try:
        f = h5py.File(path, "r")
    except OSError as error:
        raise ShardError(f"{path} is not a readable HDF5 shard, it is truncated or corrupt "
                         f"({_first_line(error)}): {fix}") from None
    try:
        yield f
    except KeyError as error:  # an HDF5 file, but not one of ours
        raise ShardError(f"{path} does not follow the shard schema (no {error}): {fix}") from None
    finally:
        f.close()


class ShardReader:
    """Random access to one shard's frames; the file opens on first use (so it can be handed
    to DataLoader worker processes unopened) and stays open."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.is_file():
            raise ShardError(f"shard {self.path} does not exist")
        with _open(self.path, FRAME_SHARD_FIX) as f:
            version = int(f.attrs.get("schema_version", -1))
            if version != SCHEMA_VERSION:
                raise ShardError(f"{self.path} has schema_version {version}, this code reads {SCHEMA_VERSION}: re-render it")
            if "images" not in f:
                raise ShardError(f"{self.path} is not a frame shard (no 'images'){' but a RefineNet patch shard' if 'patches' in f else ''}: "
                                 f"give a folder of frame shards from python -m datagen.render")
            # A shard of random boards (datagen.render --family) has a board per frame and no single board.
            self.family: dict | None = json.loads(f.attrs["family"]) if "family" in f.attrs else None
            if self.family is None:
                self._board: BoardSpec | None = BoardSpec.from_json(f.attrs["board"])
                self._boards: list[str] | None = None
            else:
                self._board = None
                self._boards = [v.decode() if isinstance(v, bytes) else str(v) for v in f["boards"][()]]
            self.generator = json.loads(f.attrs["generator"])
            self.image_size = tuple(int(v) for v in f.attrs["image_size"])
            self.meta_keys = list(f["meta"].keys())
            self._length = int(f["images"].shape[0])
            self.has_markers = "marker_ids" in f
            self.has_dist = "dist" in f
        self._file: h5py.File | None = None

    @property
    def board(self) -> BoardSpec:
        """The board every frame shows. A shard of random boards has none: `ShardError` saying so
        (a reader made for one board cannot use it), `board_of` gives each frame's."""
        if self._board is None:
            families = ", ".join(self.family.get("families", [])) if self.family else ""
            raise ShardError(f"{self.path} holds frames of random boards (datagen.render --family {families}), one "
                             f"board per frame, not one board: read each frame's board (FrameLabels.board, "
                             f"ShardReader.board_of), or render shards of one board with --board")
        return self._board

    @property
    def single_board(self) -> bool:
        """True for a shard of one board (`board`), False for one of random boards (`board_of`)."""
        return self._board is not None

    def board_of(self, i: int) -> BoardSpec:
        """The board frame ``i`` shows."""
        return self._board if self._board is not None else _board_from_json(self._boards[i])

    @property
    def max_corners(self) -> int:
        """The most inner corners of any frame's board (the padded ``corners`` width of a shard of random boards)."""
        if self._board is not None:
            return self._board.num_corners
        return max(_board_from_json(text).num_corners for text in self._boards)

    @property
    def max_markers(self) -> int:
        """The most markers of any frame's board."""
        if self._board is not None:
            return self._board.num_markers
        return max(_board_from_json(text).num_markers for text in self._boards)

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
        board = self.board_of(i)
        # Arrays padded for a shard of random boards are cut back to this frame's board.
        corners, markers = board.num_corners, board.num_markers
        try:
            for key in self.meta_keys:
                value = f["meta"][key][i]
                meta[key] = value.decode() if isinstance(value, bytes) else value.item()
            marker_labels = None
            if self.has_markers:
                marker_labels = MarkerLabels(ids=f["marker_ids"][i][:markers], corners=f["marker_corners"][i][:markers],
                                             centres=f["marker_centres"][i][:markers],
                                             visible=f["marker_visible"][i][:markers])
            return FrameLabels(image=f["images"][i], corners=f["corners"][i][:corners], visible=f["visible"][i][:corners],
                               K=f["K"][i], rvec=f["rvec"][i], tvec=f["tvec"][i], meta=meta, board=board,
                               markers=marker_labels, dist=f["dist"][i] if self.has_dist else None)
        except OSError as error:  # a damaged chunk: HDF5 only finds out when it reads it
            raise ShardError(f"frame {i} of {self.path} cannot be read ({_first_line(error)}): the shard is corrupt; "
                             f"{FRAME_SHARD_FIX}") from None

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_file": None}  # h5py handles do not cross processes


@lru_cache(maxsize=4096)
def _board_from_json(text: str) -> BoardSpec:
    return BoardSpec.from_json(text)


PATCH_SIZE = 24


def write_patch_shard(directory: str | Path, index: int, patches: np.ndarray, offsets: np.ndarray, meta: dict,
                      generator: dict, created: str | None = None) -> Path:
    """Write a RefineNet patch shard (docs/conventions.md): ``patches`` uint8 (N, 24, 24), ``offset`` float32 (N, 2)
    = the corner's position inside the patch in pixels (OpenCV convention), ``meta/*`` 1-D per patch
    (``source`` required). Atomic like `write_shard`."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    n = len(patches)
    if n == 0 or patches.dtype != np.uint8 or patches.shape[1:] != (PATCH_SIZE, PATCH_SIZE):
        raise ShardError(f"patches must be uint8 (N>0, {PATCH_SIZE}, {PATCH_SIZE}), got {patches.dtype} {patches.shape}")
    if offsets.shape != (n, 2) or not np.all(np.isfinite(offsets)):
        raise ShardError(f"offsets must be finite (N, 2) = ({n}, 2), got {offsets.shape}")
    if "source" not in meta:
        raise ShardError("patch meta must hold 'source' (e.g. 'render' or 'synthetic')")
    final = directory / shard_name(index)
    with _hdf5_atomic(final, index) as f:
        f.attrs["schema_version"] = SCHEMA_VERSION
        f.attrs["generator"] = json.dumps(generator, sort_keys=True)
        f.attrs["patch_size"] = PATCH_SIZE
        f.attrs["created"] = created or creation_time()
        f.create_dataset("patches", data=patches, chunks=(min(n, 1024), PATCH_SIZE, PATCH_SIZE),
                         compression="gzip", compression_opts=4, shuffle=True, track_times=False)
        f.create_dataset("offset", data=offsets.astype(np.float32), track_times=False)
        group = f.create_group("meta", track_order=True)
        for key, values in meta.items():
            data = np.asarray(values)
            if data.dtype.kind in "US":
                data = np.array([str(v) for v in values], dtype=h5py.string_dtype())
            if data.shape != (n,):
                raise ShardError(f"patch meta {key!r} must be one scalar per patch")
            group.create_dataset(key, data=data, track_times=False)
    return final


def read_patch_shard(path: str | Path) -> tuple[np.ndarray, np.ndarray, dict]:
    """(patches (N, 24, 24) uint8, offsets (N, 2) float32, meta) of one patch shard (a few MB: read whole)."""
    path = Path(path)
    if not path.is_file():
        raise ShardError(f"patch shard {path} does not exist (make some with python -m datagen.patches)")
    with _open(path, PATCH_SHARD_FIX) as f:
        if "patches" not in f:
            raise ShardError(f"{path} is not a patch shard (no 'patches' dataset){' but a frame shard' if 'images' in f else ''}: "
                             f"give a folder of patch shards from python -m datagen.patches")
        meta = {key: f["meta"][key][()] for key in f["meta"]}
        return f["patches"][()], f["offset"][()], meta
