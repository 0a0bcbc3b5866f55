"""Look at a render: ``python -m datagen.inspect data/renders`` -> counts, histograms, a mosaic.

Writes ``<DIR>/inspect/mosaic.png`` (random frames as the network sees them, labelled
corners drawn with their IDs: green visible, red occluded or outside) and
``<DIR>/inspect/histograms.png`` (lux, blur, visible corners, exposure and gain), and prints
a summary. Frames are shown unaltered: a dark frame must look dark.
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

import cv2
import numpy as np

from datagen.shards import ShardReader, list_shards
from deepcharuco.cli.common import output_folder, run_command
from deepcharuco.core.errors import DeepCharucoError

NUMERIC = ("lux", "blur_px", "visible_count", "exposure_s", "gain", "dist_k1", "bend", "squares_x", "squares_y")
CATEGORICAL = ("has_board", "board_kind", "hdri", "shake", "spot", "shadow_caster", "occluder", "distractors", "lamps",
               "dictionary", "legacy", "inverted", "mirrored")


def collect_meta(paths: list[Path]) -> dict[str, np.ndarray]:
    """Every frame's meta, concatenated over shards: {key: (N,) array}."""
    columns: dict[str, list] = {}
    for path in paths:
        reader = ShardReader(path)
        handle = reader._handle()
        for key in reader.meta_keys:
            values = handle["meta"][key][()]
            columns.setdefault(key, []).append(np.array([v.decode() if isinstance(v, bytes) else v for v in values]))
        reader.close()
    return {key: np.concatenate(parts) for key, parts in columns.items()}


def draw_labels(image: np.ndarray, corners: np.ndarray, visible: np.ndarray, scale: int = 2) -> np.ndarray:
    """(H*scale, W*scale, 3) BGR tile with the labelled corners and their IDs."""
    tile = cv2.resize(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR), None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    for corner_id, (corner, seen) in enumerate(zip(corners, visible)):
        if not np.all(np.isfinite(corner)):
            continue
        centre = tuple(int(round((c + 0.5) * scale - 0.5)) for c in corner)
        colour = (0, 220, 0) if seen else (0, 0, 230)
        cv2.circle(tile, centre, 3, colour, 1, cv2.LINE_AA)
        cv2.putText(tile, str(corner_id), (centre[0] + 4, centre[1] - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35, colour, 1, cv2.LINE_AA)
    return tile


def mosaic(paths: list[Path], count: int, rng: np.random.Generator, columns: int = 4, scale: int = 1) -> np.ndarray:
    """A grid of ``count`` random frames with their labels and a caption (lux, blur, kind)."""
    readers = [ShardReader(p) for p in paths]
    sizes = np.array([len(r) for r in readers])
    picks = rng.choice(sizes.sum(), size=min(count, int(sizes.sum())), replace=False)
    starts = np.cumsum(sizes) - sizes
    tiles = []
    for pick in sorted(picks):
        shard = int(np.searchsorted(starts, pick, side="right") - 1)
        frame = readers[shard][int(pick - starts[shard])]
        tile = draw_labels(frame.image, frame.corners, frame.visible, scale)
        caption = (f"{frame.meta.get('lux', float('nan')):.1f} lx  blur {frame.meta.get('blur_px', 0):.1f}px"
                   + ("" if frame.meta["has_board"] else "  NEGATIVE"))
        cv2.rectangle(tile, (0, tile.shape[0] - 14), (tile.shape[1], tile.shape[0]), (0, 0, 0), -1)
        cv2.putText(tile, caption, (3, tile.shape[0] - 3), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(tile)
    for reader in readers:
        reader.close()
    blank = np.zeros_like(tiles[0])
    tiles += [blank] * (-len(tiles) % columns)
    rows = [np.hstack(tiles[i:i + columns]) for i in range(0, len(tiles), columns)]
    return np.vstack(rows)


def histograms(meta: dict[str, np.ndarray], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [k for k in NUMERIC if k in meta]
    if not keys:  # shards from a writer that records none of them (evaluate.paper.autolabel's captures)
        figure, axis = plt.subplots(figsize=(3.2, 2.8))
        axis.text(0.5, 0.5, "no numeric meta", ha="center", va="center")
        figure.savefig(path, dpi=90)
        plt.close(figure)
        return
    figure, axes = plt.subplots(1, len(keys), figsize=(3.2 * len(keys), 2.8))
    for axis, key in zip(np.atleast_1d(axes), keys):
        values = meta[key].astype(float)
        if key in ("lux", "exposure_s") and np.all(values > 0):
            axis.hist(values, bins=np.geomspace(values.min(), values.max() * 1.001, 30))
            axis.set_xscale("log")
        else:
            axis.hist(values, bins=30)
        axis.set_title(key)
    figure.tight_layout()
    figure.savefig(path, dpi=90)
    plt.close(figure)


def summary(meta: dict[str, np.ndarray], shards: int) -> str:
    n = len(meta["has_board"])
    lines = [f"{n} frames in {shards} shard(s); {int((~meta['has_board'].astype(bool)).sum())} negatives"]
    for key in NUMERIC:
        if key in meta:
            p = np.percentile(meta[key].astype(float), [0, 5, 50, 95, 100])
            lines.append(f"  {key:>13}: min {p[0]:.3g}  p5 {p[1]:.3g}  median {p[2]:.3g}  p95 {p[3]:.3g}  max {p[4]:.3g}")
    for key in CATEGORICAL:
        if key in meta:
            counts = Counter(meta[key].tolist())
            lines.append(f"  {key:>13}: " + ", ".join(f"{k}: {v}" for k, v in sorted(counts.items(), key=lambda kv: str(kv[0]))))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m datagen.inspect", formatter_class=argparse.ArgumentDefaultsHelpFormatter,
                                     description="Counts, histograms and a labelled mosaic of a folder of frame shards.")
    parser.add_argument("dir", help="folder of shard-*.h5 written by python -m datagen.render")
    parser.add_argument("--out", default=None, help="where to write the PNGs (default: DIR/inspect)")
    parser.add_argument("--frames", type=int, default=24, help="frames in the mosaic")
    parser.add_argument("--columns", type=int, default=6)
    parser.add_argument("--scale", type=int, default=1, help="mosaic tile magnification")
    parser.add_argument("--seed", type=int, default=0, help="which random frames the mosaic shows")
    args = parser.parse_args(argv)

    def body() -> None:
        paths = list_shards(args.dir)
        if not paths:
            raise DeepCharucoError(f"{args.dir} holds no complete shards (render some with python -m datagen.render)")
        meta = collect_meta(paths)  # reads every shard: a damaged one is named before anything is written
        out = output_folder(args.out or Path(args.dir) / "inspect")
        print(summary(meta, len(paths)))
        image = mosaic(paths, args.frames, np.random.default_rng(args.seed), args.columns, args.scale)
        if not cv2.imwrite(str(out / "mosaic.png"), image):
            raise DeepCharucoError(f"could not write {out / 'mosaic.png'} (disk full?): free some space or choose another --out")
        histograms(meta, out / "histograms.png")
        print(f"wrote {out / 'mosaic.png'} and {out / 'histograms.png'}")

    return run_command(body)

if __name__ == "__main__":
    sys.exit(main())
