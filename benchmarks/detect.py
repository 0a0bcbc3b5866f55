"""Detection speed at real resolutions, every configuration next to OpenCV, in one interleaved run.

    python benchmarks/detect.py [--frames data/sequences] [--count 10] [--sizes 320x240,640x480,1280x720,1920x1080]

Frames: ``--count`` well-lit frames of the report's rendered sequences (``--frames``, the frames its
synthetic protocols start from; ``python -m evaluate.sequences --out data/sequences`` renders them), each
scaled to fill the frame at every size (letterboxed: the board grows with the image, its
camera matrix and truth scaled with it), and the same frames darkened (the paper's darkness
k=7: ~3 % of the light). Without the test set, views of the board drawn by
`deepcharuco.synthetic` are used instead (said in the output). One extra row puts the 320x240
frames unscaled in the middle of a 1920x1080 frame: a small board far away.

Each configuration runs the full pipeline of the speed issue (detect + estimate_pose with the
frame's K); `evaluate.protocols.time_pipelines` interleaves them (A B C A B C ...) so that load
on the machine hits all alike, and the table gives fps, the ratio to OpenCV's fps measured in
the same run, the fraction of true corners found within 3 px (the paper's accuracy: speed is never
bought with missed boards) and their mean distance to the truth in px (the sub-pixel error at full
resolution, next to OpenCV's).

The report's boards the shipped weights never saw (`evaluate.unseen_boards.UNSEEN_BOARDS`: 7x5 DICT_6X6_250,
11x8 DICT_5X5_1000, 4x5 DICT_4X4_1000 printed inverted; found by their markers, `geometry="markers"`, with the
weights `Detector(board)` picks) are timed on ``--count`` drawn 320x240 views of each, lit and dark, next to
OpenCV and hybrid.

A last table times video: the first frame drifting 2 px a frame for 30 frames, searched whole
every frame (OpenCV, the deep detector) or tracked (`deepcharuco.tracking.BoardTracker`: only
around the last board, the whole frame every 30), in good light and dark.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import torch

from deepcharuco import BoardSpec, OpenCVDetector
from deepcharuco.deep_detector import Detector
from deepcharuco.pose import project_corners
from deepcharuco.runtime import int8_model, onnxruntime_available
from deepcharuco.synthetic import look_at_pose, render_board_view
from deepcharuco.tracking import BoardTracker
from evaluate.data import TestSetError, load_frames, select_well_lit
from evaluate.machine import cpu_description
from evaluate.protocols import TestFrame, darken, score_corners, time_pipelines
from evaluate.unseen_boards import UNSEEN_BOARDS

DARK_K = 7


def letterboxed(frame: TestFrame, size: tuple[int, int], scale: float | None = None) -> TestFrame:
    """``frame`` scaled by ``scale`` (default: as large as fits ``size``) and centred on a grey canvas of
    ``size`` (W, H); truth and camera matrix follow (pixel centres: x' = (x + 0.5) s - 0.5 + offset)."""
    width, height = size
    h, w = frame.image.shape
    scale = min(width / w, height / h) if scale is None else scale
    new_w, new_h = round(w * scale), round(h * scale)
    left, top = (width - new_w) // 2, (height - new_h) // 2
    interpolation = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    image = np.full((height, width), int(np.median(frame.image)), np.uint8)
    image[top:top + new_h, left:left + new_w] = cv2.resize(frame.image, (new_w, new_h), interpolation=interpolation)
    sx, sy = new_w / w, new_h / h
    to_new = np.array([[sx, 0, 0.5 * sx - 0.5 + left], [0, sy, 0.5 * sy - 0.5 + top], [0, 0, 1]])
    corners = (frame.corners + 0.5) * np.array([sx, sy], np.float32) - 0.5 + np.array([left, top], np.float32)
    return replace(frame, image=image, corners=corners.astype(np.float32), K=to_new @ frame.K)


def darkened(frame: TestFrame, k: int = DARK_K) -> TestFrame:
    return replace(frame, image=darken(frame.image, k))


def drawn_frames(board: BoardSpec, count: int, seed: int = 0) -> list[TestFrame]:
    """``count`` 320x240 views of ``board`` drawn with random tilts and distances (no Blender needed)."""
    rng = np.random.default_rng(seed)
    K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
    frames = []
    for i in range(count):
        rvec, tvec = look_at_pose(board, rng.uniform(0.35, 0.6), rng.uniform(-35, 35), rng.uniform(-35, 35),
                                  rng.uniform(-30, 30), tuple(rng.uniform(-0.03, 0.03, 2)))
        image = render_board_view(board, K, rvec, tvec, background=int(rng.integers(40, 160)))
        corners = project_corners(board, rvec, tvec, K).astype(np.float32)
        frames.append(TestFrame(image, corners, np.ones(len(corners), bool), K, rvec, tvec, f"drawn#{i}"))
    return frames


def drifting_clip(frame: TestFrame, length: int = 30, step_px: float = 2.0) -> list[np.ndarray]:
    """``length`` images of ``frame`` moving right by ``step_px`` a frame (a board waved slowly in a video)."""
    height, width = frame.image.shape
    border = int(np.median(frame.image))
    return [cv2.warpAffine(frame.image, np.float32([[1, 0, i * step_px], [0, 1, 0]]), (width, height),
                           borderMode=cv2.BORDER_CONSTANT, borderValue=border) for i in range(length)]


def clip_fps(detector, clip: list[np.ndarray], rounds: int = 3) -> tuple[float, float]:
    """(fps, fraction of frames with >= 4 corners) of ``detector`` over ``clip`` in order, median of rounds."""
    rates, found = [], 0
    for _ in range(rounds):
        if isinstance(detector, BoardTracker):
            detector.reset()
        started = time.perf_counter()
        found = sum(len(detector.detect(image)) >= 4 for image in clip)
        rates.append(len(clip) / (time.perf_counter() - started))
    return float(np.median(rates)), found / len(clip)


def accuracy(detector, frames: list[TestFrame]) -> tuple[float, float]:
    """(fraction of visible true corners found within 3 px, mean distance of those to the truth in px)."""
    right, visible, errors = 0, 0, []
    for frame in frames:
        score = score_corners(detector.detect(frame.image), frame)
        right += score.num_correct
        visible += int(frame.visible.sum())
        errors.extend(score.subpixel_errors)
    return right / max(visible, 1), float(np.mean(errors)) if errors else float("nan")


def pipelines(board: BoardSpec, backends: list[str]) -> dict:
    """Every configuration to time, by name: OpenCV (+cornerSubPix), the deep detector per backend, hybrid."""
    configurations = {"opencv": OpenCVDetector(board, refine="subpix")}
    for backend in backends:
        configurations[f"deep {backend}"] = Detector(board, backend=backend)
    configurations["hybrid"] = Detector(board, mode="hybrid")
    return configurations


def parse_size(text: str) -> tuple[int, int]:
    width, _, height = text.partition("x")
    return int(width), int(height)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", default="data/sequences",
                        help="the report's rendered sequences (default: data/sequences)")
    parser.add_argument("--count", type=int, default=10, help="well-lit frames used (default: 10)")
    parser.add_argument("--sizes", default="320x240,640x480,1280x720,1920x1080", help="frame sizes WxH")
    parser.add_argument("--seconds", type=float, default=3.0, help="timing per configuration and row (default: 3)")
    parser.add_argument("--threads", type=int, default=None, help="torch/ONNX Runtime threads (default: torch's)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)

    board = BoardSpec()
    try:
        base = select_well_lit(load_frames(args.frames, board), count=args.count)
        source = f"{args.count} well-lit frames of {args.frames}"
    except TestSetError as error:
        base = drawn_frames(board, args.count)
        source = f"{args.count} drawn views ({error})"
    backends = ["torch"] + (["onnx"] if onnxruntime_available() else [])
    configurations = pipelines(board, backends)
    deep = Detector(board)
    if onnxruntime_available() and int8_model(deep.checkpoint) is not None:
        configurations["deep onnx-int8"] = Detector(board, backend="onnx-int8")
    print(f"# {cpu_description()}, {torch.get_num_threads()} threads, torch "
          f"{torch.__version__}, OpenCV {cv2.__version__}; default backend: {deep.runner.name}")
    print(f"# frames: {source}; full pipeline: detect + estimate_pose")

    rows = []
    for text in args.sizes.split(","):
        size = parse_size(text)
        rows.append((f"{size[0]}x{size[1]}", [letterboxed(f, size) for f in base]))
        rows.append((f"{size[0]}x{size[1]} dark k={DARK_K}", [darkened(letterboxed(f, size)) for f in base]))
    rows.append(("1920x1080 small board", [letterboxed(f, (1920, 1080), scale=1.0) for f in base]))

    names = list(configurations)
    print(f"{'frames':28s} " + " ".join(f"{n:>30s}" for n in names))
    print(f"{'':28s} " + " ".join(f"{'fps (x OpenCV) acc err':>30s}" for _ in names))
    for label, frames in rows:
        fps = time_pipelines(configurations, frames, rounds=3, min_seconds=args.seconds)
        cells = []
        for name in names:
            right, error = accuracy(configurations[name], frames)
            cells.append(f"{fps[name]:7.1f} ({fps[name] / fps['opencv']:5.2f}x) {right:5.2f} {error:5.2f}")
        print(f"{label:28s} " + " ".join(f"{c:>30s}" for c in cells), flush=True)

    # Boards the weights never saw, found by their markers (geometry="markers") with the weights `Detector(board)`
    # picks (a family model where one ships): drawn 320x240 views.
    for name, unseen in UNSEEN_BOARDS.items():
        others = {"opencv": OpenCVDetector(unseen, refine="subpix"), "deep": Detector(unseen),
                  "hybrid": Detector(unseen, mode="hybrid")}
        print(f"\nboard never seen in training ({name}), read by its markers with "
              f"{Path(others['deep'].weights).name}: {args.count} drawn 320x240 views")
        drawn = drawn_frames(unseen, args.count)
        for label, frames in (("320x240", drawn), (f"320x240 dark k={DARK_K}", [darkened(f) for f in drawn])):
            fps = time_pipelines(others, frames, rounds=3, min_seconds=args.seconds)
            cells = [f"{fps[n]:7.1f} ({fps[n] / fps['opencv']:5.2f}x) " + "{:5.2f} {:5.2f}".format(*accuracy(d, frames))
                     for n, d in others.items()]
            print(f"{label:28s} " + " ".join(f"{c:>30s}" for c in cells), flush=True)

    # Video: the first frame drifting 2 px a frame, searched whole each frame or tracked (BoardTracker).
    print("\nvideo, 30 frames drifting 2 px/frame: fps (frames with >= 4 corners)")
    video = {"opencv": configurations["opencv"], "deep": deep, "deep tracked": BoardTracker(deep),
             "hybrid tracked": BoardTracker(configurations["hybrid"])}
    print(f"{'frames':28s} " + " ".join(f"{n:>18s}" for n in video))
    for text in args.sizes.split(","):
        size = parse_size(text)
        for label, frame in ((f"{text}", letterboxed(base[0], size)),
                             (f"{text} dark k={DARK_K}", darkened(letterboxed(base[0], size)))):
            clip = drifting_clip(frame)
            cells = [clip_fps(detector, clip) for detector in video.values()]
            print(f"{label:28s} " + " ".join(f"{f:9.1f} ({r:4.2f})".rjust(18) for f, r in cells), flush=True)


if __name__ == "__main__":
    main()
