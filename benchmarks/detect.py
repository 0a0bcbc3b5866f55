"""Detection speed on the frames users point a camera at, every detector next to OpenCV in one interleaved run.

    python benchmarks/detect.py [--count 8] [--sizes 320x240,640x480,1280x720,1920x1080]
                                [--realdata realdata] [--seconds 3] [--skip-videos] [--candidate runs/fast]
                                [--network auto]

``--realdata``: a folder of capture folders as docs/evaluation.md's "Real captures" lists them (caliscope's
calibration session with its frames_review.csv, ...; each with its board.yaml). Without it, the backgrounds
are procedural clutter only and no real video is timed.

Frames (`evaluate.speed.realistic`, seed ``--seed``): the paper's board drawn into cluttered backgrounds (procedural
clutter, and real webcam frames without a board from ``--realdata``) at 30-95 % of the width at
320x240 and at 10-30 % and 50-95 % at the larger sizes; the same frames darkened (the paper's darkness k=7,
~3 % of the light); frames with no board at all; a 3x3 board (4 corners, DICT_5X5_100) at 8-15 % of a
2592x1944 (5 MP) frame; the report's boards the shipped weights never saw, on clutter; and every frame of
each real video under ``--realdata`` (searched whole, and tracked with `BoardTracker` as ``deepcharuco
detect`` does for videos), lit and darkened.

Each detector runs what a user runs (detect + estimate_pose with the frame's K);
`evaluate.paper.protocols.time_pipelines` interleaves them (A B C A B C ...) so that load on the machine hits all
alike. Per row: fps, the ratio to OpenCV (+ cornerSubPix) in the same run, the share of true corners found
within 3 px, the corners reported that are wrong (frames without a board: every corner is), and where the
deep detector's time goes (ms a frame per stage, `deepcharuco.core.stage_times`).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from deepcharuco import BoardSpec, OpenCVDetector
from deepcharuco.cli.detect import CAMERA_SEARCH_EVERY, VIDEO_SEARCH_EVERY
from deepcharuco.core.stage_times import StageTimes, stage
from deepcharuco.detection.deep_detector import Detector
from deepcharuco.detection.parallel import flushed, settled
from deepcharuco.detection.tracking import BoardTracker
from deepcharuco.networks.shipped import NETWORKS
from evaluate.paper.protocols import TestFrame, darken, score_corners, time_pipelines
from evaluate.paper.unseen_boards import UNSEEN_BOARDS
from evaluate.speed.machine import cpu_description, gpu_name
from evaluate.speed.realistic import Placement, clutter, fit, real_backgrounds, video_frames, with_board, without_board

DARK_K = 7
SMALL, LARGE, FILLING = Placement(0.10, 0.30), Placement(0.50, 0.95), Placement(0.30, 0.95)
FIVE_MP = (2592, 1944)
TINY_BOARD = BoardSpec(squares_x=3, squares_y=3, square_length=0.04, marker_length=0.03, dictionary="DICT_5X5_100")
STAGE_GROUPS = ("network", "candidates", "board check", "markers", "refine", "corner fit", "pose", "other")


def parse_size(text: str) -> tuple[int, int]:
    width, _, height = text.partition("x")
    return int(width), int(height)


def backgrounds_for(size: tuple[int, int], count: int, rng: np.random.Generator, real: list[np.ndarray]
                    ) -> list[np.ndarray]:
    """``count`` backgrounds of ``size``: procedural clutter, every other one a real frame where there are some."""
    return [fit(real[(i // 2) % len(real)], size) if real and i % 2 else clutter(rng, size) for i in range(count)]


def board_rows(board: BoardSpec, sizes: list[tuple[int, int]], count: int, rng: np.random.Generator,
               real: list[np.ndarray]) -> list[tuple[str, list[TestFrame]]]:
    rows = []
    for size in sizes:
        label = f"{size[0]}x{size[1]}"
        placements = [("30-95%", FILLING)] if size[0] <= 320 else [("10-30%", SMALL), ("50-95%", LARGE)]
        for name, placement in placements:
            frames = [with_board(board, background, rng, placement, f"{label} #{i}")
                      for i, background in enumerate(backgrounds_for(size, count, rng, real))]
            rows.append((f"{label} board {name}", frames))
            rows.append((f"{label} board {name} dark", [darkened(f) for f in frames]))
        if size[0] > 320:
            rows.append((f"{label} no board", [without_board(b, f"{label} empty #{i}")
                                               for i, b in enumerate(backgrounds_for(size, count, rng, real))]))
    return rows


def darkened(frame: TestFrame, k: int = DARK_K) -> TestFrame:
    return replace(frame, image=darken(frame.image, k), name=frame.name + " dark")


def scores(detector, frames: list[TestFrame]) -> tuple[float, int]:
    """(share of the true corners found within 3 px, corners reported that are not), over ``frames``."""
    right, visible, wrong = 0, 0, 0
    for frame in frames:
        score = score_corners(detector.detect(frame.image), frame)
        right += score.num_correct
        visible += int(frame.visible.sum())
        wrong += score.num_detected - score.num_correct
    return (right / visible if visible else float("nan")), wrong


def stage_breakdown(detector: Detector, frames: list[TestFrame]) -> tuple[dict[str, float], float]:
    """(ms a frame per `STAGE_GROUPS` group, search levels a frame) of ``detector`` over ``frames`` (one pass)."""
    with StageTimes() as times:
        started = time.perf_counter()
        for frame in frames:
            detection = detector.detect(frame.image)
            with stage("pose"):
                detector.estimate_pose(detection, frame.K)
        total = time.perf_counter() - started
    groups = dict.fromkeys(STAGE_GROUPS, 0.0)
    for name, seconds in times.seconds.items():
        group = "network" if name.startswith("network") else name
        groups[group if group in groups else "other"] += seconds
    groups["other"] += max(total - sum(groups.values()), 0.0)  # what no stage names: levels made, glue
    return {k: 1000 * v / len(frames) for k, v in groups.items()}, times.counts["levels"] / len(frames)


def print_row(label: str, cells: list[str], width: int) -> None:
    print(f"{label:34s} " + " ".join(f"{c:>{width}s}" for c in cells), flush=True)


Candidate = tuple[str, dict]  # a second set of deep and hybrid detectors: (its label, `Detector`'s keywords)


def candidate_of(weights: Path | None, network: str | None) -> Candidate | None:
    """``--candidate`` (weights, a bundle or a weights folder: `Detector(weights=...)`) or ``--network``."""
    if weights is not None:
        return "candidate", {"weights": weights}
    return None if network is None else (network, {"network": network})


def detector_set(board: BoardSpec, device: str, candidate: Candidate | None) -> dict:
    """OpenCV (+ cornerSubPix), the deep and the hybrid detector with the shipped lite networks, and with
    ``candidate`` the deep and hybrid detectors with its weights or networks too."""
    detectors = {"opencv": OpenCVDetector(board, refine="subpix"), "deep": Detector(board, device=device),
                 "hybrid": Detector(board, mode="hybrid", device=device)}
    if candidate is not None:
        label, options = candidate
        detectors[f"deep, {label}"] = Detector(board, device=device, **options)
        detectors[f"hybrid, {label}"] = Detector(board, mode="hybrid", device=device, **options)
    return detectors


def time_rows(rows: list[tuple[str, list[TestFrame]]], detectors: dict, seconds: float) -> None:
    names = list(detectors)
    print_row("frames", names, 27)
    print_row("", ["fps (x OpenCV) acc wrong"] * len(names), 27)
    breakdowns = []
    for label, frames in rows:
        fps = time_pipelines(detectors, frames, rounds=3, min_seconds=seconds)
        cells = []
        for name in names:
            right, wrong = scores(detectors[name], frames)
            cells.append(f"{fps[name]:6.1f} ({fps[name] / fps['opencv']:5.2f}x) {right:4.2f} {wrong:4d}")
        print_row(label, cells, 27)
        for name in [n for n in names if n.startswith("deep")]:
            if name in detectors:
                breakdowns.append((name, label, *stage_breakdown(detectors[name], frames)))
    for name in dict.fromkeys(b[0] for b in breakdowns):
        print(f"\nwhere the {name} detector's time goes, ms a frame (one pass; levels: search levels run a frame)")
        print_row("frames", [*STAGE_GROUPS, "levels"], 11)
        for _, label, groups, levels in (b for b in breakdowns if b[0] == name):
            print_row(label, [f"{groups[g]:.1f}" for g in STAGE_GROUPS] + [f"{levels:.1f}"], 11)


def video_rows(realdata: Path, device: str = "cpu", candidate: Candidate | None = None) -> None:
    """Every frame of every video under ``realdata`` (with its folder's board.yaml), lit and darkened: fps and
    frames with >= 4 corners for OpenCV, the deep detector searching each frame whole, tracked with every level of
    every frame searched while no board is tracked, tracked as ``deepcharuco detect`` tracks a video (every level
    every `VIDEO_SEARCH_EVERY`-th frame while no board is tracked, looking back: `BoardTracker.push`) and as it
    tracks a camera (every `CAMERA_SEARCH_EVERY`-th frame, no looking back), and the hybrid detector tracked as a
    video; with ``candidate`` (`candidate_of`), its deep detector searching each frame whole and tracked as a video,
    and its hybrid tracked as a video. The detectors take the frames in turn (each frame by every detector, then the
    next), so that load on the machine hits all alike."""
    videos = sorted(realdata.glob("*/*.mp4"))
    if not videos:
        print(f"\nno real videos under {realdata}: pass --realdata")
        return
    print(f"\nreal videos, every frame in order: fps (frames with >= 4 corners); {realdata}")
    names = ["opencv", "deep", "deep tracked (1)", f"deep, video's ({VIDEO_SEARCH_EVERY})",
             f"deep, camera's ({CAMERA_SEARCH_EVERY})", "hybrid, video's"]
    if candidate is not None:
        label, options = candidate
        names += [label, f"{label}, video's", f"hybrid {label}, video's"]
    print_row("video", names, 20)
    for path in videos:
        board = BoardSpec.load(path.parent / "board.yaml")
        deep, hybrid = Detector(board, device=device), Detector(board, mode="hybrid", device=device)
        runs = {"opencv": OpenCVDetector(board, refine="subpix"), "deep": deep, names[2]: BoardTracker(deep),
                names[3]: BoardTracker(deep, search_every=VIDEO_SEARCH_EVERY),
                names[4]: BoardTracker(deep, search_every=CAMERA_SEARCH_EVERY, look_back=False),
                names[5]: BoardTracker(hybrid, search_every=VIDEO_SEARCH_EVERY)}
        if candidate is not None:
            runs[names[6]] = Detector(board, device=device, **options)
            runs[names[7]] = BoardTracker(runs[names[6]], search_every=VIDEO_SEARCH_EVERY)
            runs[names[8]] = BoardTracker(Detector(board, mode="hybrid", device=device, **options),
                                          search_every=VIDEO_SEARCH_EVERY)
        frames = video_frames(path)
        for label, clip in ((path.parent.name + "/" + path.name, frames),
                            (f"  dark k={DARK_K}", [darken(f, DARK_K) for f in frames])):
            for detector in runs.values():
                if isinstance(detector, BoardTracker):
                    detector.reset()
            # Frame by frame, each detector in turn (load on the machine hits all alike); a tracker as a video or a
            # camera: `push`, looking back or not, its held frames flushed at the end.
            seconds, detections = dict.fromkeys(names, 0.0), {name: [] for name in names}
            for frame in [*clip, None]:
                for name in names:
                    detector = runs[name]
                    started = time.perf_counter()
                    done = flushed(detector) if frame is None else settled(detector, frame)
                    seconds[name] += time.perf_counter() - started
                    detections[name] += done
            cells = [f"{len(clip) / seconds[name]:6.1f} ({sum(len(d) >= 4 for d in detections[name]):3d}/{len(clip)})"
                     for name in names]
            print_row(label, cells, 20)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--count", type=int, default=8, help="frames a row (default: 8)")
    parser.add_argument("--sizes", default="320x240,640x480,1280x720,1920x1080", help="frame sizes WxH")
    parser.add_argument("--realdata", type=Path, default=None,
                        help="folder of real capture folders: backgrounds without a board and the videos (default: none)")
    parser.add_argument("--seconds", type=float, default=3.0, help="timing per detector and row (default: 3)")
    parser.add_argument("--seed", type=int, default=0, help="frames' seed (default: 0)")
    parser.add_argument("--skip-videos", action="store_true", help="leave the real videos out")
    parser.add_argument("--skip-boards", action="store_true", help="leave the drawn boards out (videos only)")
    parser.add_argument("--device", default="cpu",
                        help="where the deep detector's networks run: cpu (default), cuda, ... (PyTorch on a GPU)")
    parser.add_argument("--candidate", type=Path, default=None,
                        help="other weights to time and score beside the shipped ones in the same run: a checkpoint, "
                             "a bundle, or a folder laid out as deepcharuco/weights (e.g. distilled fast networks; "
                             "deepcharuco/weights/fast is network='fast', with the lite networks behind its tracking)")
    parser.add_argument("--network", choices=[n for n in NETWORKS if n != "lite"], default=None,
                        help="time and score the deep and hybrid detectors with these networks (Detector's network: "
                             "auto, deepcharuco detect's default, or fast) beside the lite ones in the same run")
    args = parser.parse_args()
    if args.count < 1:
        parser.error("--count must be >= 1")
    if args.candidate is not None and args.network is not None:
        parser.error("give --candidate or --network, not both")
    candidate = candidate_of(args.candidate, args.network)

    rng = np.random.default_rng(args.seed)
    real = [] if args.realdata is None else real_backgrounds(args.realdata / "caliscope_calibration", limit=24)
    board = BoardSpec()
    deep = Detector(board, device=args.device)
    print(f"# {cpu_description()}, OpenCV {cv2.__version__}; deep backend {deep.runner.name} on {args.device}"
          + (f" ({gpu_name(args.device)})" if args.device != "cpu" else ""))
    print("# backgrounds: procedural clutter" + (f" and {len(real)} real frames without a board" if real else
                                                " only (--realdata holds no caliscope_calibration review)"))
    print("# each detector: detect + estimate_pose; 'deep' = Detector(board), 'hybrid' = Detector(board, mode='hybrid')"
          " (the lite networks; deepcharuco detect's default is hybrid with network='auto')")
    if not args.skip_boards:
        sizes = [parse_size(s) for s in args.sizes.split(",")]
        detectors = detector_set(board, args.device, candidate)
        print(f"\nthe paper's board ({board.squares_x}x{board.squares_y} {board.dictionary}), {args.count} frames a row")
        time_rows(board_rows(board, sizes, args.count, rng, real), detectors, args.seconds)

        frames = [with_board(TINY_BOARD, b, rng, Placement(0.08, 0.15), f"5MP #{i}")
                  for i, b in enumerate(backgrounds_for(FIVE_MP, max(2, args.count // 2), rng, real))]
        tiny = detector_set(TINY_BOARD, args.device, candidate)
        print(f"\na 3x3 board (4 corners, {TINY_BOARD.dictionary}) at 8-15 % of a {FIVE_MP[0]}x{FIVE_MP[1]} frame")
        time_rows([("5 MP tiny board", frames), ("5 MP tiny board dark", [darkened(f) for f in frames])], tiny,
                  args.seconds)

        for name, unseen in UNSEEN_BOARDS.items():
            others = detector_set(unseen, args.device, candidate)
            print(f"\nboard never seen in training ({name}), read by its markers, on clutter")
            frames = [with_board(unseen, b, rng, FILLING, f"{name} #{i}")
                      for i, b in enumerate(backgrounds_for((640, 480), args.count, rng, real))]
            time_rows([("640x480 board 30-95%", frames), ("640x480 board 30-95% dark", [darkened(f) for f in frames])],
                      others, args.seconds)
    if args.skip_videos:
        return
    if args.realdata is None:
        print("\nno real videos timed: pass --realdata (docs/evaluation.md, Real captures)")
        return
    video_rows(args.realdata, args.device, candidate)


if __name__ == "__main__":
    main()
