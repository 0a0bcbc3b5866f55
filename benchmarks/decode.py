"""The deep detector's decoding (the markers' search and checks, `placement.corners_from_markers`) on real webcam
frames, next to OpenCV + cornerSubPix in the same interleaved run.

    python benchmarks/decode.py --realdata realdata [--step 4] [--rounds 3] [--plain] [--network fast]

Frames: every ``--step``-th frame of each video of ``--realdata``/caliscope_calibration (four 1280x720 webcams),
and every other one of them darkened (k = 7). Each frame is detected once as `Detector.detect` searches a whole frame,
and every call it makes to `corners_from_markers` (every search level, every region) is recorded; then, interleaved
round by round (A B C A B C ...): OpenCV + cornerSubPix on every frame, the recorded decoding calls replayed (one core:
numpy's BLAS single-threaded, as `Detector.detect` runs it), and `Detector.detect` on every frame. Reported: ms a frame
(medians over rounds, wall time and the process' CPU time) and each as a multiple of OpenCV's time in the same run
(x OpenCV: 2.0 = twice as long).

``--network``: the point network whose candidates are decoded (`Detector`'s ``network``: "lite", the default, or
"fast"; a fast network's candidates differ, so do the calls). ``--plain``: the decoding's numpy paths, not
`decode_kernel`'s compiled loops (also what runs without numba).
Run it against another checkout of the package (``PYTHONPATH=other/checkout``) to compare versions: it uses only
`Detector`, `OpenCVDetector` and `placement.corners_from_markers`.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from deepcharuco import BoardSpec, OpenCVDetector
import deepcharuco.detection.deep_detector as deep_detector
from deepcharuco.detection.markers import lattice, marker_reader, placement
from deepcharuco.detection.markers.placement import corners_from_markers
from deepcharuco.core.blas import single_threaded_blas
from deepcharuco.networks.shipped import NETWORKS
from evaluate.captures.reader import video_frames
from evaluate.paper.protocols import darken
from evaluate.speed.machine import cpu_description

DARK_K = 7


def load_frames(folder: Path, step: int) -> list[np.ndarray]:
    """Every ``step``-th grey frame of each video in ``folder``, then every other one of those darkened."""
    frames = [gray for video in sorted(folder.glob("*.mp4")) for _, gray in video_frames(video, step, None)]
    return frames + [darken(frame, DARK_K) for frame in frames[::2]]


def record_decoding(detector, frames: list[np.ndarray]) -> tuple[list[tuple[tuple, dict]], int]:
    """Every `corners_from_markers` call ``detector.detect`` makes on ``frames`` -> (the calls' arguments, frames
    with >= 4 corners)."""
    calls = []

    def recording(*args, **kwargs):
        calls.append((args, kwargs))
        return corners_from_markers(*args, **kwargs)

    original = deep_detector.corners_from_markers
    deep_detector.corners_from_markers = recording
    try:
        found = sum(len(detector.detect(frame)) >= 4 for frame in frames)
    finally:
        deep_detector.corners_from_markers = original
    return calls, found


def timed(run) -> tuple[float, float]:
    """(wall seconds, process CPU seconds) of ``run()``."""
    wall, cpu = time.perf_counter(), time.process_time()
    run()
    return time.perf_counter() - wall, time.process_time() - cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--realdata", type=Path, required=True, help="folder holding caliscope_calibration/")
    parser.add_argument("--step", type=int, default=4, help="every step-th frame of each video (default: 4)")
    parser.add_argument("--rounds", type=int, default=3, help="interleaved timing rounds (default: 3)")
    parser.add_argument("--plain", action="store_true", help="the decoding's numpy paths (no numba kernels)")
    parser.add_argument("--network", choices=NETWORKS, default="lite",
                        help="the point network whose candidates are decoded (default: lite)")
    args = parser.parse_args()
    folder = args.realdata / "caliscope_calibration"
    if not (folder / "board.yaml").is_file():
        print(f"error: {folder}/board.yaml not found: pass --realdata, the folder holding caliscope_calibration/ "
              f"(docs/evaluation.md, Real captures)", file=sys.stderr)
        raise SystemExit(2)
    if args.step < 1 or args.rounds < 1:
        parser.error("--step and --rounds must be >= 1")
    compiled = getattr(marker_reader, "compiled_kernel", None) is not None
    if args.plain:
        marker_reader.compiled_kernel = lattice.compiled_kernel = placement.compiled_kernel = None
        compiled = False
    board = BoardSpec.load(folder / "board.yaml")
    frames = load_frames(folder, args.step)
    detector = deep_detector.Detector(board, network=args.network)
    opencv = OpenCVDetector(board, refine="subpix")
    calls, found = record_decoding(detector, frames)
    print(f"# {cpu_description()}, OpenCV {cv2.__version__}; deepcharuco from {Path(deep_detector.__file__).parent}; "
          f"decoding {'compiled (numba)' if compiled else 'numpy'}; {args.network} network")
    print(f"# {len(frames)} frames {frames[0].shape[1]}x{frames[0].shape[0]} (every {args.step}th of {folder.name}'s "
          f"videos, every other one also darkened k={DARK_K}); the deep detector finds >= 4 corners in {found}; "
          f"{len(calls)} decoding calls ({len(calls) / len(frames):.1f} a frame)")

    def opencv_pass():
        for frame in frames:
            opencv.detect(frame)

    def decoding_pass():
        with single_threaded_blas():
            for call_args, call_kwargs in calls:
                corners_from_markers(*call_args, **call_kwargs)

    def deep_pass():
        for frame in frames:
            detector.detect(frame)

    runs = {"opencv + cornerSubPix": opencv_pass, "decoding (one core)": decoding_pass, "deep, searched whole": deep_pass}
    times: dict[str, list[tuple[float, float]]] = {name: [] for name in runs}
    for _ in range(args.rounds):
        for name, run in runs.items():
            times[name].append(timed(run))
    base_wall = statistics.median(t[0] for t in times["opencv + cornerSubPix"])
    base_cpu = statistics.median(t[1] for t in times["opencv + cornerSubPix"])
    print(f"{'':24s} {'ms a frame (wall)':>18s} {'x OpenCV':>9s} {'ms a frame (CPU)':>17s} {'x OpenCV':>9s} {'fps':>6s}")
    for name in runs:
        wall = statistics.median(t[0] for t in times[name])
        cpu = statistics.median(t[1] for t in times[name])
        print(f"{name:24s} {1000 * wall / len(frames):18.1f} {wall / base_wall:9.2f} {1000 * cpu / len(frames):17.1f} "
              f"{cpu / base_cpu:9.2f} {len(frames) / wall:6.1f}")


if __name__ == "__main__":
    main()
