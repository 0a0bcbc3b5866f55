"""RefineNet patch shards cut from drawn frames, no renders needed:
``python -m train.drawn_patches --out data/patches-drawn --shards 100``.

Each shard is ``--frames`` frames drawn by `train.draw` (boards of every marker family through random poses and
lenses onto photographs and clutter, under the paper's photometric augmentations, a fifth of them inverted prints
as the detector sees them, rounded to 8-bit grey levels), rounded to uint8, with a 24x24 patch cut around each
visible corner so that the corner falls on a random pixel of the central 8x8 (`datagen.patches.cut_patches`: its
exact, drawn sub-pixel position is the label; a patch with a second corner in its centre is dropped); plus
``--synthetic`` times as many synthetic X-junctions (`datagen.patches.synthetic_patch`); then ``--shadow-edges``
of them under a cast shadow's edge (`datagen.patches.cast_shadow_edges`). The shards are the patch shards of
docs/conventions.md, which ``python -m train.refinenet --data`` reads.

Shard ``k`` is drawn from ``default_rng([seed, k])`` alone, and a shard already in ``--out`` is kept: a run
interrupted (Ctrl-C, a killed job) continues where it stopped when run again with the same options.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from datagen.patches import cast_shadow_edges, cut_patches, synthetic_patches
from datagen.shards import read_patch_shard, shard_name, write_patch_shard
from deepcharuco.boards.board import BoardSpec
from deepcharuco.cli.common import run_command
from deepcharuco.core.errors import DeepCharucoError
from train.augment import AugmentConfig
from train.distill import family_boards
from train.draw import DrawConfig, FrameDrawer

FAMILIES = ("DICT_4X4", "DICT_5X5", "DICT_6X6")
BOARDS_PER_FAMILY = 4
# A square 4-40 px near the board's centre at 160 px wide (8-80 px in the 320x240 frames drawn here): the detector
# refines corners at full resolution, where squares run from a small board's ~6 px to a near one's 100 and more.
SQUARE_PX = (4.0, 40.0)
FRAME_SIZE = (320, 240)


def boards(seed: int) -> list[BoardSpec]:
    """The paper's board and `BOARDS_PER_FAMILY` random boards of each of `FAMILIES` (RefineNet is board-agnostic:
    it sees a corner's junction and the marker bits beside it)."""
    return [BoardSpec()] + [b for family in FAMILIES for b in family_boards(family, BOARDS_PER_FAMILY, seed)]


def draw_config() -> DrawConfig:
    return replace(DrawConfig(), size=FRAME_SIZE, square_px=SQUARE_PX, inverted_p=0.2, bits=8,
                   augmentation=AugmentConfig(homography_p=0.0, min_brightness=0.005))


def shard_patches(drawer: FrameDrawer, rng: np.random.Generator, frames: int, synthetic: float, shadow_edges: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One shard's (patches (N, 24, 24) uint8, offsets (N, 2) float32, sources (N,) str), every draw from ``rng``."""
    drawn = drawer.draw(rng, frames)
    images = np.clip(np.round(drawn.image[:, 0].cpu().numpy() * 255.0), 0, 255).astype(np.uint8)
    patches, offsets = [], []
    for image, corners, visible in zip(images, drawn.corners, drawn.visible):
        cut, offset, _ = cut_patches(image, corners, visible, rng)
        patches.append(cut)
        offsets.append(offset)
    patches, offsets = np.concatenate(patches), np.concatenate(offsets)
    count = int(round(synthetic * len(patches)))
    sources = np.array(["drawn"] * len(patches) + ["synthetic"] * count)
    if count:
        more, more_offsets = synthetic_patches(rng, count)
        patches, offsets = np.concatenate([patches, more]), np.concatenate([offsets, more_offsets])
    patches, _ = cast_shadow_edges(patches, offsets, rng, shadow_edges)
    order = rng.permutation(len(patches))
    return patches[order], offsets[order].astype(np.float32), sources[order]


def parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m train.drawn_patches", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="folder of patch shards (made; shards in it are kept)")
    parser.add_argument("--shards", type=int, default=100, help="shards in all (default: 100)")
    parser.add_argument("--frames", type=int, default=256, help="drawn frames a shard (default: 256, ~2,500 patches)")
    parser.add_argument("--synthetic", type=float, default=0.25,
                        help="synthetic junctions per drawn patch (default: 0.25)")
    parser.add_argument("--shadow-edges", type=float, default=0.1,
                        help="share of the patches under a cast shadow's edge (default: 0.1)")
    parser.add_argument("--seed", type=int, default=0, help="shard k is drawn from default_rng([seed, k]) (default: 0)")
    parser.add_argument("--first", type=int, default=0,
                        help="the first shard's index (default: 0): other indices, other patches, e.g. validation")
    parser.add_argument("--device", default="cpu", help="where the frames are drawn: cpu (default), cuda, ...")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)

    def body() -> None:
        if args.shards < 1 or args.frames < 1:
            raise DeepCharucoError("--shards and --frames must be >= 1")
        if args.synthetic < 0 or not 0.0 <= args.shadow_edges <= 1.0:
            raise DeepCharucoError("--synthetic must be >= 0 and --shadow-edges a share from 0 to 1")
        drawer = FrameDrawer(boards(args.seed), draw_config(), device=args.device)
        generator = {"name": "train.drawn_patches", "seed": args.seed, "frames": args.frames,
                     "synthetic": args.synthetic, "shadow_edges": args.shadow_edges,
                     "square_px": list(SQUARE_PX), "frame_size": list(FRAME_SIZE)}
        indices = range(args.first, args.first + args.shards)
        written = 0
        for index in tqdm(indices, desc="patch shards", unit="shard"):
            if (args.out / shard_name(index)).is_file():
                read_patch_shard(args.out / shard_name(index))  # a damaged one is named, not trusted
                continue
            with torch.no_grad():
                patches, offsets, sources = shard_patches(drawer, np.random.default_rng([args.seed, index]),
                                                          args.frames, args.synthetic, args.shadow_edges)
            write_patch_shard(args.out, index, patches, offsets, {"source": sources}, generator)
            written += 1
        print(f"{written} shards written, {len(indices) - written} already there: {args.out}")

    return run_command(body)


if __name__ == "__main__":
    raise SystemExit(main())
