"""Offline throughput: frames a second through `deepcharuco.detection.parallel.DetectorPool` (what ``deepcharuco detect
--jobs N`` and ``calibrate --jobs N`` run), deep detector and OpenCV + cornerSubPix with the same number of worker
processes, in one run.

    python benchmarks/throughput.py [--jobs 1,2] [--device cpu|cuda] [--frames 400] [--realdata realdata]

Frames: the paper's board drawn into procedural clutter at 320x240 (30-95 % of the width) and at 1280x720
(10-30 %), each lit and darkened (k = 7); with ``--realdata``, every frame of caliscope's four 1280x720 webcam
videos (`caliscope_calibration/*.mp4`, their own board). A video's frames go to the workers in chunks of 16
consecutive frames, each tracked from its first frame (`BoardTracker`, looking back) or from the chunk before's
board where that frame lost it, as ``detect`` does; the drawn frames are independent and searched whole. Workers are started and warmed up before the clock runs; the frames are
read into memory first, so neither decoding the video nor starting processes is counted.
"""

from __future__ import annotations

import argparse
import time
from functools import partial
from pathlib import Path

import cv2
import numpy as np

from deepcharuco import BoardSpec
from deepcharuco.cli.detect import CHUNK_FRAMES, VIDEO_SEARCH_EVERY, make_finders
from deepcharuco.core.platform import available_cpus
from deepcharuco.detection.parallel import DetectorPool
from evaluate.paper.protocols import darken
from evaluate.speed.machine import cpu_description, gpu_name
from evaluate.speed.realistic import Placement, clutter, video_frames, with_board

DARK_K = 7


def drawn_frames(board: BoardSpec, size: tuple[int, int], placement: Placement, count: int, seed: int
                 ) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [with_board(board, clutter(rng, size), rng, placement, str(i)).image for i in range(count)]


# The pool starts its processes as work arrives, and a worker starts in seconds (PyTorch, a CUDA context). A warm-up
# of one chunk per worker, with 16 workers and chunks of one frame, left starts in the first row's clock (an H200
# machine, 2026-11-26: lit 320x240 128 frames a second, against 378 warmed with chunks of 16). So the warm-up is
# repeated until its rate stops rising.
WARM_UP_CHUNKS = 4  # a warm-up pass: chunks per worker
MAX_WARM_UP_PASSES = 8


def frames_per_second(pool: DetectorPool, frames: list[np.ndarray]) -> tuple[float, int]:
    """(frames a second, frames with >= 4 corners) of ``pool`` over ``frames``, after warm-up passes over its first
    ones until a pass is no more than 10 % faster than the one before (every worker has started)."""
    warm_up, rate = frames[:WARM_UP_CHUNKS * pool.workers * pool.chunk], 0.0
    for _ in range(MAX_WARM_UP_PASSES):
        started = time.perf_counter()
        for _ in pool.detect((None, f) for f in warm_up):
            pass
        rate, before = len(warm_up) / (time.perf_counter() - started), rate
        if rate < 1.1 * before:
            break
    started = time.perf_counter()
    found = sum(len(detections[0]) >= 4 for _, detections in pool.detect((None, f) for f in frames))
    return len(frames) / (time.perf_counter() - started), found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--jobs", default=f"1,{available_cpus()}", help="worker counts to time (default: 1 and "
                                                                       "the CPUs)")
    parser.add_argument("--device", default="cpu", help="the deep detector's networks: cpu (default) or cuda")
    parser.add_argument("--frames", type=int, default=400, help="frames a drawn row (default: 400; 64 distinct, "
                                                                "repeated)")
    parser.add_argument("--realdata", type=Path, default=None, help="folder holding caliscope_calibration/")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    jobs = [int(j) for j in args.jobs.split(",")]

    board = BoardSpec()
    rows = []
    for size, placement in (((320, 240), Placement(0.30, 0.95)), ((1280, 720), Placement(0.10, 0.30))):
        distinct = drawn_frames(board, size, placement, min(64, args.frames), args.seed)
        frames = [distinct[i % len(distinct)] for i in range(args.frames)]
        rows.append((f"{size[0]}x{size[1]} drawn", board, frames, 1))
        rows.append((f"{size[0]}x{size[1]} drawn dark", board, [darken(f, DARK_K) for f in frames], 1))
    if args.realdata is not None:
        folder = args.realdata / "caliscope_calibration"
        video_board = BoardSpec.load(folder / "board.yaml")
        frames = [f for path in sorted(folder.glob("*.mp4")) for f in video_frames(path)]
        rows.append(("caliscope webcams, tracked", video_board, frames, CHUNK_FRAMES))

    device = gpu_name(args.device) if args.device != "cpu" else "CPU"
    print(f"# {cpu_description()}, {available_cpus()} CPUs, OpenCV {cv2.__version__}; deep on {args.device} ({device})")
    print("# frames a second (frames with >= 4 corners); ratio: deep / OpenCV with the same workers")
    print(f"{'frames':30s} {'jobs':>4s} {'OpenCV':>14s} {'deep':>14s} {'ratio':>6s}", flush=True)
    results = {}
    for workers in jobs:
        for name in ("opencv", "deep"):
            # one pool for the rows of one board and chunk: starting processes is not what is measured
            for key in dict.fromkeys((spec, chunk) for _, spec, _, chunk in rows):
                spec, chunk = key
                # a video's chunks as `detect VIDEO --jobs N` tracks them (every level every VIDEO_SEARCH_EVERY-th frame
                # while no board is tracked, looking back); drawn frames searched whole
                make = partial(make_finders, name, [spec], "subpix" if name == "opencv" else "refinenet", None, None,
                               "auto", True, args.device if name == "deep" else "cpu", 30 if chunk > 1 else 1,
                               VIDEO_SEARCH_EVERY if chunk > 1 else 1)
                with DetectorPool(make, workers, chunk=chunk) as pool:
                    for label, _, frames, _ in (row for row in rows if (row[1], row[3]) == key):
                        results[label, workers, name] = frames_per_second(pool, frames)
        for label, *_ in rows:
            cells = [results[label, workers, name] for name in ("opencv", "deep")]
            print(f"{label:30s} {workers:4d} " + " ".join(f"{fps:7.1f} ({found:4d})" for fps, found in cells)
                  + f" {cells[1][0] / cells[0][0]:6.2f}", flush=True)

if __name__ == "__main__":
    main()
