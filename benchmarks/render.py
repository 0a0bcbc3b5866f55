"""Render throughput: seconds per frame at 320x240 with 1 and 2 worker processes, in one run.

    python benchmarks/render.py [--frames 24] [--samples 4]

Prints s/frame for each worker count and the frames/s ratio (2 workers / 1 worker). The
target (issue 3) is < 0.3 s/frame on a 2-core machine: 50,000 frames in one night.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

from datagen.render import RenderJob, run
from deepcharuco.boards.board import BoardSpec


def seconds_per_frame(frames: int, workers: int, samples: int | None, seed: int) -> float:
    with tempfile.TemporaryDirectory() as out:
        cores = os.cpu_count() or 1
        job = RenderJob(n=frames, out=out, seed=seed, board=BoardSpec(), width=320, height=240, samples=samples,
                        shard_size=max(1, frames // (2 * workers)), clean=False, device="cpu",
                        threads=max(1, cores // workers))
        started = time.perf_counter()
        run(job, workers=workers, shard_index=0, num_shards=1, resume=False, recycle=10**6, quiet=True)
        return (time.perf_counter() - started) / frames


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--samples", type=int, default=None, help="Cycles samples (default: the renderer's)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    results = {workers: seconds_per_frame(args.frames, workers, args.samples, args.seed) for workers in (1, 2)}
    for workers, spf in results.items():
        print(f"{workers} worker(s): {spf:.3f} s/frame  ({1 / spf:.2f} frames/s; 50,000 frames in {50000 * spf / 3600:.1f} h)")
    print(f"scaling 1 -> 2 workers: {results[1] / results[2]:.2f}x frames/s  (cores: {os.cpu_count()})")
    print(f"target < 0.3 s/frame: {'met' if min(results.values()) < 0.3 else 'missed'}")


if __name__ == "__main__":
    main()
