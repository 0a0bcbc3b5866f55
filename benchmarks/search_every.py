"""How often a video read by `deepcharuco detect` searches every level while no board is tracked (`BoardTracker`'s
``search_every``), on drawn validation videos (`evaluate.speed.drawn_videos`): the frames each value finds, and its
speed, against every level of every frame.

    python benchmarks/search_every.py [--seed 0] [--videos 1] [--frames 150] [--values 1,3,4,6,8,12]
                                      [--network lite|fast|auto] [--detector deep|hybrid] [--camera]

Boards: the paper's (read by the shipped weights' ID head), 7x5 DICT_6X6_250 and an inverted 4x5 DICT_4X4_1000 (both
read by their markers); conditions:
good, dark and shake; ``--videos`` videos of each, drawn from ``--seed`` (0 chooses; the real videos in realdata/
measure). Each video is read by `BoardTracker.push` once per value, as ``detect VIDEO`` reads it (looking back; with
``--camera`` frame by frame, as a live camera), the values' order turned by one for each video so that load on the
machine hits all alike; OpenCV (+ cornerSubPix) reads every frame in the same run.

Per value: frames found (>= 4 corners) of the frames that show the board (>= 6 corners in the frame), frames lost and
gained against value 1, wrong corners (more than 3 px from the truth, and half the board's smear, or in a frame
without the board), ms a frame and the speed as a multiple of OpenCV's.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from tqdm import tqdm

from deepcharuco import BoardSpec, OpenCVDetector
from deepcharuco.detection.deep_detector import Detector
from deepcharuco.detection.parallel import detect_all
from deepcharuco.detection.tracking import MIN_CORNERS, BoardTracker
from evaluate.paper.unseen_boards import UNSEEN_BOARDS
from evaluate.speed.drawn_videos import CONDITIONS, DrawnVideo, drawn_video

BOARDS = {"paper 5x5 DICT_5X5_50": BoardSpec(), "7x5 DICT_6X6_250": UNSEEN_BOARDS["7x5 DICT_6X6_250"],
          "4x5 DICT_4X4_1000 inverted": UNSEEN_BOARDS["4x5 DICT_4X4_1000 inverted"]}
WRONG_PX = 3.0


def read(tracker: BoardTracker, video: DrawnVideo) -> tuple[list, float]:
    """``video`` read by ``tracker`` as ``detect VIDEO`` reads it (`parallel.detect_all`) -> (each frame's detection,
    seconds)."""
    start = time.perf_counter()
    found = detect_all(tracker, video.frames)
    return found, time.perf_counter() - start


def wrong_corners(video: DrawnVideo, detections: list) -> int:
    """Corners reported more than `WRONG_PX` from their truth, plus half the frame's smear (a smeared corner is a ramp
    that long: a wrong ID is a square away), or in frames without the board."""
    wrong = 0
    for truth, smear, detection in zip(video.corners, video.smear, detections):
        if truth is None:
            wrong += len(detection)
        elif len(detection):
            wrong += int((np.hypot(*(detection.corners - truth[detection.ids]).T) > WRONG_PX + smear / 2).sum())
    return wrong


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, default=0, help="0 chooses (validation); another seed measures")
    parser.add_argument("--videos", type=int, default=1, help="videos per board and condition (default 1)")
    parser.add_argument("--frames", type=int, default=150, help="frames a video (default 150, 5 s at 30 fps)")
    parser.add_argument("--values", default="1,3,4,6,8,12", help="search_every values; 1 is the reference")
    parser.add_argument("--network", choices=("lite", "fast", "auto"), default="lite",
                        help="the networks (Detector's network; auto: deepcharuco detect's default)")
    parser.add_argument("--detector", choices=("deep", "hybrid"), default="deep")
    parser.add_argument("--camera", action="store_true", help="frame by frame, without looking back (a live camera)")
    parser.add_argument("--conditions", nargs="+", choices=CONDITIONS, default=list(CONDITIONS))
    args = parser.parse_args(argv)
    values = [int(v) for v in args.values.split(",")]
    if 1 not in values or min(values) < 1:
        parser.error(f"--values must hold 1 (every level of every frame: the reference) and no value below 1, "
                     f"got {args.values}")
    jobs = [(name, condition, n) for name in BOARDS for condition in args.conditions for n in range(args.videos)]
    rows = {v: {"found": 0, "lost": 0, "gained": 0, "wrong": 0, "seconds": 0.0} for v in values}
    shown = frames = 0
    opencv_seconds = 0.0
    for turn, (name, condition, n) in enumerate(tqdm(jobs, desc="videos", unit="video")):
        board = BOARDS[name]
        video = drawn_video(board, seed=args.seed * 1000 + list(BOARDS).index(name) * 100 + n,
                            frames=args.frames, condition=condition)
        detector = Detector(board, network=args.network, mode=args.detector)
        detector.detect(video.frames[0])  # loads the networks before any clock starts
        shows = np.array([video.shows_board(i) for i in range(len(video.frames))])
        shown += int(shows.sum())
        frames += len(video.frames)
        found_by = {}
        order = values[turn % len(values):] + values[:turn % len(values)]
        for value in order:
            tracker = BoardTracker(detector, search_every=value, look_back=not args.camera)
            detections, seconds = read(tracker, video)
            found_by[value] = np.array([len(d) >= MIN_CORNERS for d in detections])
            rows[value]["seconds"] += seconds
            rows[value]["wrong"] += wrong_corners(video, detections)
        opencv = OpenCVDetector(board)
        start = time.perf_counter()
        for frame in video.frames:
            opencv.detect(frame)
        opencv_seconds += time.perf_counter() - start
        for value in values:
            rows[value]["found"] += int((found_by[value] & shows).sum())
            rows[value]["lost"] += int((found_by[1] & ~found_by[value] & shows).sum())
            rows[value]["gained"] += int((~found_by[1] & found_by[value] & shows).sum())
    how = "frame by frame (a camera)" if args.camera else "looking back (a video)"
    print(f"\n{len(jobs)} drawn 1280x720 videos (seed {args.seed}), {frames} frames, {shown} showing the board; "
          f"{args.detector}, {args.network} networks, {how}; OpenCV {1000 * opencv_seconds / frames:.1f} ms a frame\n")
    print("| search_every | frames found | lost / gained against 1 | wrong corners | ms a frame | x OpenCV |")
    print("|---|---|---|---|---|---|")
    for value in values:
        row = rows[value]
        print(f"| {value} | {row['found']} of {shown} | {row['lost']} / {row['gained']} | {row['wrong']} | "
              f"{1000 * row['seconds'] / frames:.1f} | {opencv_seconds / row['seconds']:.2f}x |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
