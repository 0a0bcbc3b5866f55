"""``python -m deepcharuco.detect``: find the board (and its pose) in images, a video or a camera.

Writes, into --out: an overlay (PNG per image, MP4 for a video or camera) and per-frame
results as CSV (written as frames arrive) and JSON (written at the end, also on Ctrl-C).

In a folder, an image that cannot be read (or whose depth has no known scale) is skipped with a message and
counted in the summary (and in the JSON's ``skipped``); the others go on. An image the --camera file does not fit
(another aspect ratio) gets its corners without a pose, and a warning. A folder's overlays are named after the
images (``a.png`` -> ``a.png``); images that share a name but not the extension (``a.png``,
``a.jpg``) get the extension in the overlay's name (``a_png.png``, ``a_jpg.png``), so no overlay
overwrites another. An overlay that cannot be written (a full disk) is an error, exit code 2.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from contextlib import ExitStack
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from deepcharuco.boards.board import BoardSpec, check_boards_apart
from deepcharuco.cli.common import (four_term_note, jobs_warning, load_board, no_empty_folders_on_failure,
                                    output_folder, run_command)
from deepcharuco.cli.draw import draw_detection
from deepcharuco.cli.outputs import CSV_FIELDS, CSV_SIGNATURE, JSON_START, OVERLAY_MARK, Overlays, csv_row, frame_record
from deepcharuco.cli.sources import Source, frame_numbers, open_source
from deepcharuco.core.errors import CameraFileError, DeepCharucoError
from deepcharuco.core.files import (
    atomic_file, mp4_mark, png_mark, refuse_foreign, starts_with, write_atomic,
)
from deepcharuco.core.image import to_gray_u8
from deepcharuco.detection.board_hints import what_matches
from deepcharuco.detection.opencv_detector import OpenCVDetector
from deepcharuco.detection.parallel import DetectorPool
from deepcharuco.detection.tracking import BoardTracker, StreamFrames
from deepcharuco.geometry.camera import Camera, read_camera
from deepcharuco.networks.backends import BACKENDS
from deepcharuco.networks.shipped import NETWORKS, default_network, network_weights


# Frames kept (spread over the source, every HINT_STRIDE-th of a camera's, until the board is found) to say what
# they show when no frame has the board.
HINT_FRAMES, HINT_STRIDE = 12, 5
CHUNK_FRAMES = 16  # consecutive video frames a --jobs worker takes at once (`deepcharuco.detection.parallel`)


# --search-every's default for a camera (`BoardTracker`'s search_every). Measured on caliscope's four 1280x720 webcam
# videos and its dim one read as a stream (docs/detector.md, 2026-11-26): 3 gave 1.2-2.3x the frames a second of 1,
# lit and dark, and found the same frames but 13 of the 684 with a board (cam_1's 5 lit and 5 dark, port_2's 3 dark):
# boards of small squares (22-34 px on cam_1), found a frame or two later. On the drawn validation videos
# (`python benchmarks/search_every.py --camera --detector hybrid`, 2026-11-28, seventh session), against every level
# of every frame: 2 lost 17 of 717 frames at 1.6x the speed, 3 lost 30 at 2.0x, 6 lost 57 at 2.7x. A board entering
# is found a frame or two late; a live stream that outruns the detector loses more than that, so 3 stays.
CAMERA_SEARCH_EVERY = 3


# --search-every's default for a video. A video looks back (`BoardTracker.push`): the frames that found nothing wait
# for the next frame that finds the board, which looks for it in them. Chosen on drawn validation videos
# (`python benchmarks/search_every.py`, seed 0: 12 videos, 1,035 frames showing the board; docs/detector.md,
# 2026-11-28, seventh session), against every level of every frame: 3 lost 8 of 720 frames with the default hybrid
# detector at 1.8x its speed, and 3 of 679 with the fast networks at 1.4x; 6 lost 24 and 11 (2.3x, 1.6x); 12 lost 31
# and 11 (2.7x, 1.8x). The frames first, so 3.
VIDEO_SEARCH_EVERY = 3


def make_detector(name: str, board: BoardSpec | None, refine: str, weights: str | None = None,
                  refine_weights: str | None = None, backend: str = "auto", corner_fit: bool = True,
                  device: str = "cpu", network: str = "lite"):
    """"opencv", "deep" or "hybrid" (OpenCV first, the networks where its corners do not verify); ``corner_fit``:
    the deep and hybrid detectors place corners last by the printed-pattern fit (`deepcharuco.detection.corner_fit`);
    ``device``: where their networks run ("cuda": PyTorch on the GPU); ``network``: which (`Detector`'s)."""
    if name == "opencv":
        if refine == "refinenet":
            raise DeepCharucoError("--refine refinenet needs --detector deep or hybrid; OpenCV takes subpix or none")
        return OpenCVDetector(board, refine=refine)
    from deepcharuco.detection.deep_detector import Detector

    return Detector(board=board, weights=weights, refine=refine, refine_weights=refine_weights,
                    mode="hybrid" if name == "hybrid" else "deep", backend=backend, corner_fit=corner_fit,
                    device=device, network=network)


def make_finders(name: str, boards: list[BoardSpec | None], refine: str, weights: str | None,
                 refine_weights: str | None, backend: str, corner_fit: bool, device: str, refresh_every: int,
                 search_every: int = 1, look_back: bool = True, network: str = "lite") -> list:
    """One finder per board, as a worker process of ``--jobs`` makes them (`deepcharuco.detection.parallel`) for a video
    or a camera: the detector, wrapped in a `BoardTracker` where ``refresh_every`` > 1, else in `StreamFrames`."""
    detectors = [make_detector(name, board, refine, weights, refine_weights, backend, corner_fit, device, network)
                 for board in boards]
    return [stream_finder(d, refresh_every, search_every, look_back) for d in detectors]


def stream_finder(detector, refresh_every: int, search_every: int, look_back: bool):
    """``detector`` for a video's or a camera's frames: a `BoardTracker` where ``refresh_every`` > 1, else each frame
    searched whole (`StreamFrames`: a stream's frames, as a tracker's whole searches are, where the fast networks'
    lite backup searches fewer of them)."""
    if refresh_every > 1:
        return BoardTracker(detector, refresh_every, search_every, look_back)
    return StreamFrames(detector)


def _camera_for(camera: Camera | None, shape: tuple[int, ...]) -> Camera | None:
    return None if camera is None else camera.for_image_size(shape[1], shape[0])


@dataclass
class _BoardRun:
    """One board's part of a run: its detector (and tracker), its output files and what it found."""

    board_file: str | None
    detector: object
    finder: object
    csv_path: Path
    json_path: Path
    records: list[dict] = field(default_factory=list)
    found: bool = False
    samples: list[np.ndarray] = field(default_factory=list)


def board_names(paths: list[str]) -> list[str]:
    """The suffix each board's output files get when several boards are given: their files' stems, refused when
    two are alike."""
    names = [Path(p).stem for p in paths]
    for name in names:
        if names.count(name) > 1:
            raise DeepCharucoError(f"two --board files are named {name}: each board's results are <source>_{name}.csv, "
                                   f"so give board files of different names")
    return names


def run(args: argparse.Namespace) -> dict:
    """Detect in every frame of ``args.source`` and write the results into ``args.out``; returns the JSON summary
    (of the first board, where several are given), whose ``complete`` is False when Ctrl-C stopped the run (what
    was done is written all the same). Several ``--board`` files: each board is searched in every frame and gets
    its own ``<source>_<board file stem>.csv`` / ``.json``; the overlay shows them all."""
    args.network = args.network or default_network(args.weights, args.device, args.backend)
    network_weights(args.network, args.weights, args.device)  # a conflict with --weights or --device: refused here
    board_files = args.board or [None]
    suffixes = [""] if len(board_files) == 1 else [f"_{name}" for name in board_names(board_files)]
    boards = [load_board(path) if path else None for path in board_files]  # deep: default to the weights' board
    if len(boards) > 1:  # one detector per board below: Detector(boards=...)'s own check does not run
        check_boards_apart(boards, board_files)
    camera = read_camera(args.camera) if args.camera else None
    note = None if camera is None else four_term_note(args.camera, camera)
    if note:
        print(note, file=sys.stderr)
    detectors = [make_detector(args.detector, board, args.refine, args.weights, args.refine_weights, args.backend,
                               corner_fit=not args.no_corner_fit, device=args.device, network=args.network)
                 for board in boards]
    source = open_source(args.source, args.max_frames)
    # Consecutive frames: search around the last board (a full-frame search every --refresh-every frames). A camera's
    # frames go to --jobs workers one at a time, as they come: each is searched whole.
    tracking = source.kind == "video" or (source.kind == "camera" and args.jobs == 1)
    refresh_every = args.refresh_every if tracking else 1  # 1: every frame searched whole (`stream_finder`)
    # While no board is tracked, every level of the pyramid every --search-every frames, the coarse one between: a
    # live camera's stream outruns the detector, so it gets the quicker search unless told otherwise.
    search_every = args.search_every or (CAMERA_SEARCH_EVERY if source.kind == "camera" else VIDEO_SEARCH_EVERY)
    # A video is not watched live: frames the quick search found nothing in wait for the next that finds the board,
    # which looks back through them (`BoardTracker.push`).
    look_back = source.kind == "video"
    out = output_folder(args.out)
    runs = [_BoardRun(path, detector,
                      stream_finder(detector, refresh_every, search_every, look_back)
                      if source.kind in ("video", "camera") else detector,
                      out / f"{source.stem}{suffix}.csv", out / f"{source.stem}{suffix}.json")
            for path, detector, suffix in zip(board_files, detectors, suffixes)]
    for board_run in runs:
        refuse_foreign(board_run.csv_path, starts_with(CSV_SIGNATURE.encode()), "detection CSV", args.force)
        refuse_foreign(board_run.json_path, starts_with(JSON_START), "detection JSON", args.force)
    if not args.no_overlay:
        for path in Overlays(out, source).images():
            refuse_foreign(path, png_mark(OVERLAY_MARK), "PNG overlay written by deepcharuco detect", args.force)
        video = Overlays(out, source).video_path()
        if video is not None:
            refuse_foreign(video, mp4_mark(OVERLAY_MARK), "video overlay written by deepcharuco detect", args.force)
    if camera is None:
        print("no --camera given: detecting corners only, no pose", file=sys.stderr)
    if getattr(detectors[0], "weights", None) is not None:
        behind = getattr(detectors[0], "backup_weights", None)  # named, not built: a photo may never need them
        backup = "" if behind is None else f"; the lite networks behind them: {behind}"
        print(f"weights: {detectors[0].weights} (decoding: {detectors[0].geometry}{backup})", file=sys.stderr)

    overlays = Overlays(out, source)
    interrupted = False
    hint_stride = max(1, (source.total or HINT_FRAMES * HINT_STRIDE) // HINT_FRAMES)  # spread over the source
    frames_read = 0
    unposed: list[str] = []  # a folder's images the camera file does not fit
    scaled_to: list[tuple[int, int]] = []  # frame sizes the camera file's intrinsics were scaled to
    # The CSVs are written as frames arrive, under temporary names renamed into place at the end (also after
    # Ctrl-C): a full disk or a kill never leaves a cut-off <stem>.csv in place of a complete one.
    with ExitStack() as files:
        writers = []
        for board_run in runs:
            rows = csv.DictWriter(files.enter_context(atomic_file(board_run.csv_path, "w", newline="")),
                                  fieldnames=CSV_FIELDS)
            rows.writeheader()
            writers.append(rows)
        detect_seconds, total_seconds = None, 0.0
        jobs = 1 if source.kind == "image" else args.jobs
        if jobs == 1:
            pool = DetectorPool(lambda: [board_run.finder for board_run in runs])
        else:
            print(f"detecting on {jobs} worker processes", file=sys.stderr)
            warning = jobs_warning(jobs)
            if warning:
                print(warning, file=sys.stderr)
            pool = DetectorPool(partial(make_finders, args.detector, boards, args.refine, args.weights,
                                        args.refine_weights, args.backend, not args.no_corner_fit, args.device,
                                        refresh_every, search_every, look_back, args.network),
                                jobs, chunk=1 if source.kind == "camera" else CHUNK_FRAMES)
        files.callback(pool.close)
        try:
            results = pool.detect(((number, name, frame), to_gray_u8(frame))
                                  for number, name, frame in frame_numbers(source))
            progress = tqdm(results, total=source.total, unit="frame", disable=source.kind == "image" or args.quiet)
            mark = time.perf_counter()
            for index, ((number, name, frame), detections) in enumerate(progress):
                # One worker: reading and detecting this frame. Several: the time between results (they detect while
                # this process writes), what the run delivers.
                now = time.perf_counter()
                elapsed = now - mark
                total_seconds += elapsed
                frames_read += 1
                # Live detection speed (an exponential average: a camera's rate changes as the board moves), beside
                # the mean the JSON reports: alone, a slow stretch (no board in view) read as the run's speed.
                detect_seconds = elapsed if detect_seconds is None else 0.9 * detect_seconds + 0.1 * elapsed
                progress.set_postfix_str(f"detect {1.0 / max(detect_seconds, 1e-9):.1f} fps now, "
                                         f"{(index + 1) / max(total_seconds, 1e-9):.1f} mean", refresh=False)
                try:
                    frame_camera = _camera_for(camera, frame.shape)
                    if frame_camera is not camera and frame_camera.image_size not in scaled_to:
                        scaled_to.append(frame_camera.image_size)
                        print(f"note: {args.camera} is for {camera.image_size[0]}x{camera.image_size[1]} and "
                              f"{name} is {frame_camera.image_size[0]}x{frame_camera.image_size[1]}: its intrinsics "
                              f"are scaled to it (right for a resized stream; a cropped or binned sensor mode needs "
                              f"its own calibration)", file=sys.stderr)
                except CameraFileError as error:
                    if source.kind != "images":  # every frame of a video is this size: the run cannot pose any
                        raise
                    frame_camera = None  # one image of a folder (a stray screenshot): its corners, without a pose
                    unposed.append(f"{name}: {error}; its corners are written without a pose")
                overlay = frame if frame.ndim == 2 or frame.shape[2] == 3 else cv2.cvtColor(frame, cv2.COLOR_BGRA2BGR)
                for board_run, rows, detection in zip(runs, writers, detections):
                    # through the camera's own model (a fisheye's too: `deepcharuco.estimate_pose` given the Camera)
                    pose = board_run.detector.estimate_pose(detection, frame_camera) if frame_camera else None
                    record = frame_record(number, name, detection, pose,  # its number in the recording
                                          None if source.video is None else source.video.times.get(number))
                    board_run.records.append(record)
                    if not board_run.found and len(detection):
                        board_run.found, board_run.samples = True, []  # the board is there: no hint needed
                    elif not board_run.found and len(board_run.samples) < HINT_FRAMES and index % hint_stride == 0:
                        board_run.samples.append(to_gray_u8(frame))
                    rows.writerow(csv_row(record))
                    if not args.no_overlay:
                        overlay = draw_detection(overlay, detection, pose, frame_camera, board_run.detector.board)
                if not args.no_overlay:
                    overlays.add(name, overlay)
                mark = time.perf_counter() if jobs == 1 else now
        except KeyboardInterrupt:
            interrupted = True
            print(f"interrupted after {frames_read} frames; writing what was done (marked incomplete)", file=sys.stderr)
        finally:
            overlays.close(keep=frames_read > 0)
        if frames_read == 0 and not interrupted:  # leaving the block discards the CSVs: nothing is written
            problems = source.problems()
            raise DeepCharucoError(f"no frames could be read from {args.source}"
                                   + (f" ({problems[0]})" if problems else "")
                                   + ": give an image, a folder of images, a video with frames or a camera index "
                                     "that delivers them")
    summaries = [_finish(board_run, args, source, camera, interrupted, total_seconds, len(runs) > 1, unposed,
                         scaled_to)
                 for board_run in runs]
    return summaries[0]


def _finish(board_run: _BoardRun, args: argparse.Namespace, source: Source, camera: Camera | None, interrupted: bool,
            total_seconds: float, several: bool, unposed: list[str], scaled_to: list[tuple[int, int]]) -> dict:
    """Write one board's JSON, say what it found (``unposed``: a folder's images the camera file does not fit;
    ``scaled_to``: the frame sizes its intrinsics were scaled to),
    and return its summary."""
    records, board, detector = board_run.records, board_run.detector.board, board_run.detector
    problems = source.problems() + unposed
    if records and not board_run.found:
        problems.append(f"no board corners in any of {len(records)} frames ({args.detector} detector, board "
                        f"{board.squares_x}x{board.squares_y} {board.dictionary}{', inverted' if board.inverted else ''}"
                        f"); {what_matches(board_run.samples, board, board_run.board_file)}")
    summary = {
        "board": board.to_dict(),
        "detector": repr(detector),
        # the file's own intrinsics; a pose of a frame of another size used them scaled to it (``scaled_to``)
        "camera": None if camera is None else {"K": camera.K.tolist(), "dist": camera.dist.tolist(),
                                               "image_size": list(camera.image_size), "model": camera.model,
                                               "scaled_to": [list(size) for size in scaled_to]},
        # False: stopped by Ctrl-C before the source's end; the frames listed are all that were looked at.
        "complete": not interrupted,
        "frames": records,
        "skipped": source.skipped,
        "problems": problems,
        "detect_fps": len(records) / total_seconds if total_seconds > 0 else None,
        # the video's frame rate as its container gives it (frames' own times: each record's time_s); None for images
        "video_fps": source.fps if source.kind in ("video", "camera") else None,
    }
    write_atomic(board_run.json_path, json.dumps(summary))
    with_pose = sum(r["pose"] is not None for r in records)
    for line in problems:
        print(f"warning: {line}", file=sys.stderr)
    found = sum(r["num_corners"] > 0 for r in records)
    lost = [f"{len(source.skipped)} image(s) skipped (each named above)"] if source.skipped else []
    if source.video is not None and source.video.skipped:
        lost.append(f"{source.video.skipped_frames} undecodable frame(s) skipped")
    which = f" board {Path(board_run.board_file).stem}:" if several else ""
    print(f"{len(records)} frames{' (incomplete: interrupted)' if interrupted else ''},{which} board corners in {found}, "
          f"pose in {with_pose}{''.join(f', {line}' for line in lost)} -> {board_run.json_path.parent}/")
    return summary


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m deepcharuco.detect",
        description="Find the ChArUco board (and its pose) in images, a video or a camera; write an "
                    "overlay and per-frame results (CSV, JSON) into --out.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("source", help="image file, folder of images, video file, or camera index (0, 1, ...)")
    parser.add_argument("--board", action="append", default=None,
                        help="board description (.json/.yaml); default: the paper's 5x5 DICT_5X5_50 board. Given "
                             "several times: every board is searched in each frame, each with its own "
                             "<source>_<board file name>.csv/.json (boards of other dictionaries or first_marker_id)")
    parser.add_argument("--camera", help="OpenCV intrinsics YAML (camera_matrix, distortion_coefficients, "
                                         "image_width, image_height); without it no pose is estimated")
    parser.add_argument("--detector", choices=["opencv", "deep", "hybrid"], default="hybrid",
                        help="which detector. hybrid (the default): OpenCV first, the networks only where OpenCV's "
                             "corners do not fit one view of the board; chosen by measurement "
                             "(benchmarks/detect.py, docs/detector.md): in good light OpenCV's corners, placed by the "
                             "printed-pattern fit, at 0.47-0.83x its speed, in the dark (k = 7) the deep detector's "
                             "0.97-1.00 of the corners where "
                             "OpenCV finds none. deep: the networks always; opencv: OpenCV + cornerSubPix alone")
    parser.add_argument("--backend", choices=list(BACKENDS), default="auto",
                        help="deep/hybrid: how the networks run (auto: ONNX Runtime when installed, int8 when the "
                             "weights carry an accepted int8 model; else PyTorch)")
    parser.add_argument("--jobs", type=int, default=1,
                        help="worker processes that detect frames side by side (a folder, a video, a camera; each "
                             "worker's network gets CPUs / jobs threads): up to ~jobs x the frames a second where the "
                             "cores are there. A video's frames go to them in chunks of %d, each tracked from its "
                             "first frame, or from the chunk before's board where that frame lost it; a camera's one "
                             "at a time, each searched whole" % CHUNK_FRAMES)
    parser.add_argument("--device", default="cpu",
                        help="deep/hybrid: where the networks run: cpu, or a PyTorch device such as cuda (needs "
                             "PyTorch with CUDA; the decoding stays on the CPU, so --jobs helps there too)")
    parser.add_argument("--refresh-every", type=int, default=30,
                        help="video/camera: search the whole frame at least every N frames, in between only around "
                             "the last board found (1: whole frames always)")
    parser.add_argument("--search-every", type=int, default=None,
                        help="video/camera, deep/hybrid: while no board is tracked, search every level of the frame "
                             "every N frames and only the coarse level (320 px) between, where a board of squares "
                             "~12 px there is found at once and a smaller one up to N - 1 frames late (a video: "
                             "found there too, by looking back from the frame that finds it); a frame without a "
                             "board searched so costs 6-17x less (default: %d for a camera, %d for a video; 1: "
                             "every level of every frame)" % (CAMERA_SEARCH_EVERY, VIDEO_SEARCH_EVERY))
    parser.add_argument("--refine", choices=["subpix", "none", "refinenet"], default=None,
                        help="corner refinement (default: subpix for opencv, refinenet for deep and hybrid, as "
                             "calibrate and the Detector API)")
    parser.add_argument("--no-corner-fit", action="store_true",
                        help="deep and hybrid: leave out the printed-pattern fit that places each corner last and gives "
                             "its uncertainty (~2 ms a frame faster on a 2-core CPU; corners ~5x less exact)")
    parser.add_argument("--weights", default=None, help="--detector deep: ChArUcoNet checkpoint or bundle, or a "
                                                         "folder of them laid out as deepcharuco/weights "
                                                         "(default: the shipped weights for the board: the paper's "
                                                         "board's own, else its marker family's model where one "
                                                         "is shipped)")
    parser.add_argument("--network", choices=NETWORKS, default=None,
                        help="deep/hybrid: auto (the default on a CPU with the shipped weights): the distilled fast "
                             "networks first, the lite ones wherever those find too little (a lost board, a photo; "
                             "a video's dim frame: the fast ones again at full resolution): lite's frames, at the "
                             "fast networks' speed in good light. "
                             "fast: the lite networks only where a tracked board is lost and in dim photos (2-4x "
                             "less network time, fewer dark and steep boards in a video). lite (the default with "
                             "--weights or on a GPU): the lite networks alone. docs/detector.md; auto and fast not "
                             "with --weights")
    parser.add_argument("--refine-weights", default=None, help="--detector deep --refine refinenet: RefineNet "
                                                                "checkpoint when --weights holds only ChArUcoNet")
    parser.add_argument("--out", default="detect_out", help="output folder")
    parser.add_argument("--max-frames", type=int, default=None, help="stop after this many frames")
    parser.add_argument("--no-overlay", action="store_true", help="write results only, no overlay images/video")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--force", action="store_true",
                        help="overwrite <source>.csv / .json in --out even where they are not this command's files")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.refresh_every < 1:
        parser.error(f"--refresh-every must be >= 1 (1: search whole frames always), got {args.refresh_every}")
    if args.jobs < 1:
        parser.error(f"--jobs must be >= 1 (1: detect in this process), got {args.jobs}")
    if args.search_every is not None and args.search_every < 1:
        parser.error(f"--search-every must be >= 1 (1: every level of every frame), got {args.search_every}")
    if args.max_frames is not None and args.max_frames < 1:
        parser.error(f"--max-frames must be >= 1 (leave it out for every frame), got {args.max_frames}")
    args.refine = args.refine or ("subpix" if args.detector == "opencv" else "refinenet")

    def body() -> int:
        with no_empty_folders_on_failure(args.out):
            summary = run(args)
        return 0 if summary["complete"] else 130  # Ctrl-C: the results so far are written, marked incomplete

    return run_command(body)


if __name__ == "__main__":
    sys.exit(main())
