"""Label truth on clean renders: OpenCV's corners against the rendered labels.

    python benchmarks/labels.py [--frames 100] [--out data/renders-clean]

Renders (or reuses) ``--frames`` clean frames (well lit, unblurred, noiseless sensor, 64 spp)
and prints the median / 95th percentile distance between the labels and OpenCV's corners,
with and without cornerSubPix. Target (issue 3): < 0.1 px median, < 0.3 px p95.
"""

from __future__ import annotations

import argparse
import subprocess
import sys

import numpy as np

from datagen.shards import ShardReader, list_shards
from deepcharuco import BoardSpec, OpenCVDetector


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--out", default="data/renders-clean")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=100)
    args = parser.parse_args()
    subprocess.run([sys.executable, "-m", "datagen.render", "--clean", "--n", str(args.frames), "--seed", str(args.seed),
                    "--shard-size", str(max(1, args.frames // (4 * args.workers))), "--workers", str(args.workers), "--out", args.out, "--resume"], check=True)
    board = BoardSpec()
    for refine in ("subpix", "none"):
        detector = OpenCVDetector(board, refine=refine)
        errors, bias, frames, visible = [], [], 0, 0
        for path in list_shards(args.out):
            reader = ShardReader(path)
            for i in range(len(reader)):
                frame = reader[i]
                frames += 1
                visible += int(frame.visible.sum())
                detection = detector.detect(frame.image)
                for corner_id, corner in zip(detection.ids, detection.corners):
                    errors.append(np.linalg.norm(corner - frame.corners[corner_id]))
                    bias.append(corner - frame.corners[corner_id])
            reader.close()
        errors = np.array(errors)
        print(f"OpenCV refine={refine:6s}: {len(errors)} corners found of {visible} visible in {frames} frames; "
              f"error median {np.median(errors):.3f} px, p95 {np.percentile(errors, 95):.3f} px, "
              f"mean offset {np.mean(bias, axis=0).round(3).tolist()} px")


if __name__ == "__main__":
    main()
