"""RefineNet training patches: ``python -m datagen.patches --renders data/renders --out data/patches``.

A patch is 24x24 px with exactly one true corner inside its central 8x8 pixels, i.e. at an
offset in [7.5, 15.5) x [7.5, 15.5) in OpenCV's pixel convention (pixel centres 8..15); the
label is that offset. Two sources, as in the paper:

- ``render``: cut from rendered frames around visible labelled corners, the patch placed so
  the corner lands on a uniformly random pixel of the central 8x8 (its sub-pixel part is the
  render's), rejecting patches that would hold a second corner in the centre;
- ``synthetic``: an X-junction drawn area-exact at a uniformly random sub-pixel position, its
  two edges at random angles (perspective), with random contrast, brightness (down to
  near-black), blur, Gaussian and speckle noise.

``--shadow-edges P`` then lays, on a fraction P of each source's patches, the edge of a cast shadow
through or beside the corner (`cast_shadow_edges`, `datagen.shadow_edge`): one side of a straight line within 2 px of it
darkened to 10-60 %, its penumbra 0.3-4 px wide. Renders seldom put a shadow's edge on a corner,
and a RefineNet that never saw one placed such synthetic junctions 1.8 px off on average (0.13 px
without). Default 0: trained with it, RefineNet found these corners but lost precision on clean ones
(README, "Patches").

Patch shard ``k`` of the renders comes from frame shard ``k`` with generator
``default_rng([seed, k])``; synthetic shards follow with ``default_rng([seed, 10**6 + j])``; the
shadow edges of shard ``k`` draw from ``default_rng([seed, k, SHADOW_STREAM])``, so the patches
without them are the same bytes whatever P.

Every input shard is opened before any work (a truncated one is named at once), and the
patches are written into a hidden folder beside ``--out`` that replaces ``--out``'s shards only
when all are written: a run that fails or is interrupted leaves ``--out`` as it was.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import signal
import sys
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from datagen.shadow_edge import PENUMBRA_PX, SHADOW_EDGE_REACH_PX, SHADOW_LEVELS, shadow_edge_gain
from datagen.shards import PATCH_SIZE, ShardReader, list_shards, write_patch_shard
import deepcharuco
from deepcharuco.cli.common import output_folder, run_command
from deepcharuco.core.errors import DeepCharucoError

CENTRE_LOW, CENTRE_HIGH = 7.5, 15.5  # the central 8x8 pixels, as an interval of positions
SYNTHETIC_SHARD_BASE = 10**6
SUPERSAMPLE = 8
SHADOW_STREAM = 7  # the shadow edges' own generator per shard: the other draws stay as they were


def in_centre(offset: np.ndarray) -> np.ndarray:
    """(..., 2) offsets -> (...) bool: inside the central 8x8 pixels of a patch."""
    offset = np.asarray(offset)
    return np.all((offset >= CENTRE_LOW) & (offset < CENTRE_HIGH), axis=-1)


def cut_patches(image: np.ndarray, corners: np.ndarray, visible: np.ndarray, rng: np.random.Generator,
                per_corner: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Patches around the visible corners of one frame.

    Args:
        image: (H, W) uint8; corners: (C, 2) true positions (NaN: not projected); visible: (C,) bool.
    Returns:
        patches (N, 24, 24) uint8, offsets (N, 2) float32, corner ids (N,) int.
    """
    height, width = image.shape
    finite = np.all(np.isfinite(corners), axis=1)
    patches, offsets, ids = [], [], []
    for corner_id in np.flatnonzero(visible & finite):
        corner = corners[corner_id]
        for _ in range(per_corner):
            cell = rng.integers(8, 16, size=2)  # the central pixel the corner will fall on
            x0, y0 = (np.round(corner).astype(int) - cell)
            if x0 < 0 or y0 < 0 or x0 + PATCH_SIZE > width or y0 + PATCH_SIZE > height:
                continue
            offset = corner - (x0, y0)
            others = corners[finite & (np.arange(len(corners)) != corner_id)] - (x0, y0)
            if not in_centre(offset) or np.any(in_centre(others)):
                continue
            patches.append(image[y0:y0 + PATCH_SIZE, x0:x0 + PATCH_SIZE])
            offsets.append(offset)
            ids.append(corner_id)
    if not patches:
        return np.zeros((0, PATCH_SIZE, PATCH_SIZE), np.uint8), np.zeros((0, 2), np.float32), np.zeros(0, int)
    return np.stack(patches), np.asarray(offsets, np.float32), np.asarray(ids)


def synthetic_patch(rng: np.random.Generator, degrade: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """One synthetic X-junction patch and its corner offset (see the module docstring).

    ``degrade=False`` skips the brightness, blur and noise draws: an exact, area-sampled junction.
    """
    offset = rng.uniform(CENTRE_LOW, CENTRE_HIGH, size=2)
    first = rng.uniform(0.0, math.pi)
    second = first + rng.uniform(math.radians(35), math.radians(145))  # perspective skews the right angle
    normals = np.array([[-math.sin(a), math.cos(a)] for a in (first, second)])
    size = PATCH_SIZE * SUPERSAMPLE
    fine = (np.arange(size) + 0.5) / SUPERSAMPLE - 0.5  # fine pixel centres in patch pixels
    xx, yy = np.meshgrid(fine - offset[0], fine - offset[1])
    side = (normals[0, 0] * xx + normals[0, 1] * yy > 0) == (normals[1, 0] * xx + normals[1, 1] * yy > 0)
    dark, light = sorted(rng.uniform(0.0, 1.0, size=2))
    if light - dark < 0.15:
        light = min(1.0, dark + 0.15 + rng.uniform(0.0, 0.5))
    if rng.random() < 0.5:
        side = ~side  # which pair of quadrants is dark
    canvas = np.where(side, light, dark).astype(np.float32)
    patch = cv2.resize(canvas, (PATCH_SIZE, PATCH_SIZE), interpolation=cv2.INTER_AREA)
    if not degrade:
        return np.clip(np.round(patch * 255.0), 0, 255).astype(np.uint8), offset.astype(np.float32)
    patch = patch * rng.uniform(0.02, 1.0) if rng.random() < 0.5 else patch  # brightness, down to near-black
    if rng.random() < 0.5:
        patch = cv2.GaussianBlur(patch, (0, 0), rng.uniform(0.3, 1.5))
    if rng.random() < 0.5:
        patch = patch * (1.0 + rng.normal(0.0, rng.uniform(0.02, 0.2), patch.shape))  # speckle
    if rng.random() < 0.5:
        patch = patch + rng.normal(0.0, rng.uniform(0.005, 0.06), patch.shape)
    return np.clip(np.round(patch * 255.0), 0, 255).astype(np.uint8), offset.astype(np.float32)


def synthetic_patches(rng: np.random.Generator, count: int) -> tuple[np.ndarray, np.ndarray]:
    pairs = [synthetic_patch(rng) for _ in range(count)]
    return np.stack([p for p, _ in pairs]), np.stack([o for _, o in pairs])


def cast_shadow_edges(patches: np.ndarray, offsets: np.ndarray, rng: np.random.Generator, probability: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Each of ``patches`` (N, 24, 24) uint8, with ``probability``, under the edge of a cast shadow: the side of a
    straight line at a random angle, passing within `SHADOW_EDGE_REACH_PX` of the patch's corner (``offsets``
    (N, 2), patch pixels), keeps a share in `SHADOW_LEVELS` of its light, through a logistic penumbra
    `PENUMBRA_PX` wide. The corner stays where it was: the squares' edges still meet there.
    Returns (patches (N, 24, 24) uint8, shadowed (N,) bool); the input is left as it was."""
    count = len(patches)
    shadowed = rng.random(count) < probability
    angle = rng.uniform(0.0, np.pi, count)
    through = offsets + rng.uniform(-SHADOW_EDGE_REACH_PX, SHADOW_EDGE_REACH_PX, (count, 2))
    penumbra = rng.uniform(*PENUMBRA_PX, count)
    level = rng.uniform(*SHADOW_LEVELS, count)
    out = patches.copy()
    for i in np.flatnonzero(shadowed):
        gain = shadow_edge_gain(PATCH_SIZE, PATCH_SIZE, through[i], angle[i], penumbra[i], level[i])
        out[i] = np.clip(np.round(patches[i] * gain), 0, 255).astype(np.uint8)
    return out, shadowed


def replace_shards(staging: Path, out: Path) -> None:
    """Move the shards written in ``staging`` into ``out`` (its old shards removed first), then remove ``staging``."""
    out.mkdir(exist_ok=True)
    for old in list_shards(out):
        old.unlink()
    for new in list_shards(staging):
        os.replace(new, out / new.name)
    shutil.rmtree(staging)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m datagen.patches", formatter_class=argparse.ArgumentDefaultsHelpFormatter,
                                     description="Cut and synthesise 24x24 RefineNet corner patches into HDF5 shards.")
    parser.add_argument("--renders", default="data/renders", help="folder of frame shards (python -m datagen.render)")
    parser.add_argument("--out", default="data/patches", help="output folder of patch shards")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--per-corner", type=int, default=1, help="patches cut around each visible corner")
    parser.add_argument("--synthetic", type=int, default=20000, help="number of synthetic patches")
    parser.add_argument("--synthetic-shard-size", type=int, default=10000)
    parser.add_argument("--shadow-edges", type=float, default=0.0,
                        help="share of the patches (cut and synthetic) laid under a cast shadow's edge near the corner")
    parser.add_argument("--overwrite", action="store_true", help="replace patch shards already in --out")
    args = parser.parse_args(argv)
    if args.per_corner < 0 or args.synthetic < 0 or args.synthetic_shard_size < 1:
        parser.error("--per-corner and --synthetic must be >= 0, --synthetic-shard-size >= 1")
    if not 0.0 <= args.shadow_edges <= 1.0:
        parser.error(f"--shadow-edges is a share of the patches, from 0 to 1; got {args.shadow_edges}")
    out = Path(args.out)

    def body() -> None:
        sources = list_shards(args.renders) if args.per_corner else []
        if out.is_dir() and list_shards(out) and not args.overwrite:
            raise DeepCharucoError(f"{out} already holds patch shards; pass --overwrite to replace them or choose another --out")
        readers = [ShardReader(path) for path in sources]  # every input readable before anything is written
        if out.exists():
            output_folder(out)  # a writable folder, not a file
        output_folder(out.parent, "--out's folder")
        staging = out.parent / f".{out.name}.tmp-{os.getpid()}"
        staging.mkdir()
        # SIGTERM (a pipeline stopped, a job preempted): the staging folder removed and the process ended at once.
        # Not by raising in the handler: an exception raised inside h5py's C callbacks can be swallowed there, and
        # the run went on (seen: a SIGTERM'd run writing shards minutes later).
        signal.signal(signal.SIGTERM, lambda signum, frame: _stop(staging, signum))
        try:
            total = write_patches(readers, staging, args)
            replace_shards(staging, out)
        finally:
            shutil.rmtree(staging, ignore_errors=True)
        print(f"datagen.patches: {total} patches in {out}", file=sys.stderr)

    return run_command(body)


def _stop(staging: Path, signum: int) -> None:
    """End the run now for signal ``signum``: the unfinished patches removed, exit code 128 + signum."""
    shutil.rmtree(staging, ignore_errors=True)
    print(f"datagen.patches: stopped by signal {signum}; nothing written (rerun the command)", file=sys.stderr)
    sys.stderr.flush()
    os._exit(128 + signum)


def write_patches(readers: list[ShardReader], out: Path, args: argparse.Namespace) -> int:
    """Cut the patches of ``readers``' frames and synthesise ``args.synthetic`` more, as shards in ``out``;
    returns the number of patches."""
    generator = {"package": "deepcharuco", "version": deepcharuco.__version__, "command": "datagen.patches",
                 "args": {"renders": str(args.renders), "seed": args.seed, "per_corner": args.per_corner,
                          "synthetic": args.synthetic}}
    if args.shadow_edges:  # recorded only when used: shards made without it are the bytes they always were
        generator["args"]["shadow_edges"] = args.shadow_edges
    total = 0

    def shadow_edges(shard: int, patches: np.ndarray, offsets: np.ndarray) -> np.ndarray:
        if not args.shadow_edges:
            return patches
        rng = np.random.default_rng([args.seed, shard, SHADOW_STREAM])
        return cast_shadow_edges(patches, offsets, rng, args.shadow_edges)[0]

    for reader in tqdm(readers, desc="patches from renders", unit="shard"):
        shard = int(reader.path.stem.split("-")[1])
        rng = np.random.default_rng([args.seed, shard])
        per_frame = []  # (patches, offsets, corner ids, frame numbers) of each frame
        for i in range(len(reader)):
            frame = reader[i]
            patches, offsets, ids = cut_patches(frame.image, frame.corners, frame.visible, rng, args.per_corner)
            per_frame.append((patches, offsets, ids, np.full(len(ids), frame.meta["frame"])))
        reader.close()
        patches, offsets, ids, frames = (np.concatenate(column) for column in zip(*per_frame))
        if len(ids):
            patches = shadow_edges(shard, patches, offsets)
            write_patch_shard(out, shard, patches, offsets, {"source": np.array(["render"] * len(ids)),
                                                             "frame": frames, "corner_id": ids}, generator)
            total += len(ids)
    for j in tqdm(range(-(-args.synthetic // args.synthetic_shard_size)), desc="synthetic patches", unit="shard"):
        count = min(args.synthetic_shard_size, args.synthetic - j * args.synthetic_shard_size)
        patches, offsets = synthetic_patches(np.random.default_rng([args.seed, SYNTHETIC_SHARD_BASE + j]), count)
        patches = shadow_edges(SYNTHETIC_SHARD_BASE + j, patches, offsets)
        write_patch_shard(out, SYNTHETIC_SHARD_BASE + j, patches, offsets,
                          {"source": np.array(["synthetic"] * count), "frame": np.full(count, -1),
                           "corner_id": np.full(count, -1)}, generator)
        total += count
    return total


if __name__ == "__main__":
    sys.exit(main())
