"""``python -m deepcharuco.calibrate``: camera intrinsics from a video (or images, or a camera) of a ChArUco board,
or a rig of cameras from synchronised videos of one.

    python -m deepcharuco.calibrate VIDEO|FOLDER|CAMERA_INDEX --board board.yaml --out camera.yaml
    python -m deepcharuco.calibrate cam0.mp4 cam1.mp4 ... --board board.yaml --out rig/

Frames are read one at a time (a video is never loaded whole) and the board is detected in each;
only the corners are kept. Views are selected, calibrated with OpenCV, outliers rejected and the
camera re-solved (`deepcharuco.calibration`). Several sources are a rig (`calibrate_rig_into`). Writes an OpenCV FileStorage camera file that
`read_camera` and OpenCV read (`write_camera`'s nodes, then ``distortion_model``, the RMS, the
parameters' standard deviations, the distortion terms solved, the views used and their weights), and an HTML report beside it. Exit code 0,
or 2 with a one-line reason and nothing written.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec, check_boards_apart
from deepcharuco.calibration.exports import ExportRig
from deepcharuco.calibration.intrinsics import CalibrationResult, calibrate
from deepcharuco.calibration.solve import MODELS
from deepcharuco.calibration.views import (CalibrationError, FrameDetection, SelectionOptions, VIEW_WEIGHT_SPREAD,
                                           border_margin)
from deepcharuco.cli.calibration_exports import (add_export_options, export_folder, export_outputs, export_problems,
                                                refuse_foreign_exports)
from deepcharuco.cli.calibration_frames import calibration_pool, detect_views, networks_of
from deepcharuco.cli.common import check_output_folder, load_board, no_empty_folders_on_failure, run_command
from deepcharuco.cli.detect import make_detector
from deepcharuco.cli.sources import frame_numbers, open_source
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.core.files import OutputLock, refuse_foreign, starts_with, write_together
from deepcharuco.core.image import to_gray_u8
from deepcharuco.detection.parallel import DetectorPool
from deepcharuco.geometry.camera import camera_file_text, is_camera_file
from deepcharuco.networks.shipped import NETWORKS, default_network, network_weights

DETECTORS = ("opencv", "deep", "hybrid")


def detect_frames(frames, detector, *, step: int = 1, total: int | None = None, quiet: bool = False,
                  pool: DetectorPool | None = None) -> tuple[list[FrameDetection], tuple[int, int] | None]:
    """Detect the board in every ``step``-th frame of the iterable of (number, name, image) ``frames``: the number is
    the frame's in its recording (`sources.frame_numbers`: a damaged frame skipped shifts none after it), which each
    `FrameDetection` keeps and ``step`` counts.

    Returns (one `FrameDetection` per frame looked at, (width, height)); each frame is dropped as soon
    as it is detected. Frames of another size than the first raise CalibrationError. ``pool``: worker processes
    whose finders are this detector (`calibration_frames.calibration_pool`; default: ``detector`` here)."""
    size = None

    def wanted():
        nonlocal size
        for number, name, frame in frames:
            if number % step:
                continue
            gray = to_gray_u8(frame)
            if size is None:
                size = (gray.shape[1], gray.shape[0])
            elif (gray.shape[1], gray.shape[0]) != size:
                raise CalibrationError(f"frame {name} is {gray.shape[1]}x{gray.shape[0]} but the first was "
                                       f"{size[0]}x{size[1]}: calibrate frames of one camera at one resolution")
            yield (0, number, str(name), gray), gray

    detections = detect_views(wanted(), [detector], 1, pool, None if total is None else -(-total // step), quiet)
    return detections[0][0], size


def calibration_text(result: CalibrationResult, board: BoardSpec, detector: str, name: str = "camera.yaml",
                     network: str | None = None) -> str:
    """The camera file: `write_camera`'s four nodes (what `read_camera` and OpenCV's samples read), then
    the model, the RMS, the standard deviations, the views, and the per-corner uncertainty
    (``corner_sigma_px``, `CalibrationResult.corner_sigma`) with every corner's residual
    (``corner_residuals``: frame, ID, dx, dy). ``name``'s suffix picks the format (YAML, XML, JSON)."""

    def calibration_nodes(storage: cv2.FileStorage) -> None:
        if result.camera.model == "pinhole":  # write_camera names the fisheye model itself
            storage.write("distortion_model", result.model)
        storage.write("avg_reprojection_error", float(result.rms))
        storage.write("nr_of_frames", len(result.views))
        if result.std:
            storage.write("std_intrinsics_names", " ".join(result.std))
            storage.write("std_intrinsics", np.array(list(result.std.values()), np.float64).reshape(-1, 1))
        storage.write("per_view_reprojection_errors", np.asarray(result.per_view_rms, np.float64).reshape(-1, 1))
        storage.write("distortion_terms", result.terms)  # the terms solved; the others are held at 0
        if result.held_out:
            # calibration.select_terms: each choice's held-out views' RMS per axis (px), the lowest chosen.
            storage.write("held_out_terms", " | ".join(result.held_out))
            storage.write("held_out_rms_px", np.array(list(result.held_out.values()), np.float64).reshape(-1, 1))
        if len(result.view_weights):
            # calibration.weigh_views: each view's weight along its noisiest direction (1: as OpenCV weighs it).
            storage.write("view_weights", np.asarray(result.view_weights, np.float64).reshape(-1, 1))
        storage.write("corner_sigma_px", float(result.corner_sigma))
        # One row per corner used: frame, corner ID, residual x and y (px; detected minus reprojected).
        storage.write("corner_residuals", np.concatenate(
            [np.column_stack([np.full(len(v.ids), v.index), v.ids, r]) for v, r in zip(result.views, result.residuals)]
        ).astype(np.float64))
        storage.write("view_frames", np.array([v.index for v in result.views], np.int32).reshape(-1, 1))
        storage.write("detector", detector)
        if network:  # the networks of a deep or hybrid detector (--network)
            storage.write("network", network)
        storage.write("board", json.dumps(board.to_dict()))

    return camera_file_text(result.camera, name, extra=calibration_nodes)


def default_report_path(out: str | Path) -> Path:
    out = Path(out)
    return out.with_name(out.stem + "_report.html")


def check_writable(path: Path) -> None:
    """Refuse, before any work, an output that names a folder or lies where nothing can be written."""
    if path.is_dir():
        raise DeepCharucoError(f"{path} is a folder: give the camera file's name, e.g. {path / 'camera.yaml'}")
    check_output_folder(path.parent, f"{path}'s folder")


# How every calibration report begins (deepcharuco.calibration.report, titled "Calibration of ..."): what --out's
# report may overwrite without --force.
REPORT_START = b"<!doctype html><html><head><meta charset='utf-8'><title>Calibration"


def run(args: argparse.Namespace) -> CalibrationResult:
    out = Path(args.out)
    report = None if args.no_report else Path(args.report) if args.report else default_report_path(out)
    if report is not None and report.resolve() == out.resolve():
        raise DeepCharucoError(f"--report and --out both name {out}: give the report another name (default: "
                               f"{default_report_path(out).name})")
    for path in [out] + ([report] if report else []):
        check_writable(path)
    refuse_foreign(out, is_camera_file, "camera file", args.force)
    if report is not None:
        refuse_foreign(report, starts_with(REPORT_START), "calibration report", args.force,
                       "--report" if args.report else "--out's report")
    refuse_foreign_exports(args, export_folder(out, False), [out.stem])
    with no_empty_folders_on_failure(out.parent):
        out.parent.mkdir(parents=True, exist_ok=True)
        with OutputLock(out, "another calibrate"):
            return _calibrate_into(args, out, report)


def _calibrate_into(args: argparse.Namespace, out: Path, report: Path | None) -> CalibrationResult:
    board = load_board(args.board[0]) if args.board else BoardSpec()
    detector = make_detector(args.detector, board, args.refine, args.weights, network=args.network)
    source = open_source(args.source[0], args.max_frames)
    pool = calibration_pool(args.detector, [board], args.refine, args.weights, args.jobs, args.network)
    frames, size = detect_frames(frame_numbers(source), detector, step=args.step, total=source.total, quiet=args.quiet,
                                 pool=pool)
    for line in source.problems():  # damaged stretches of a video, unreadable images: said, then calibrated without
        print(f"warning: {line}", file=sys.stderr)
    if size is None:
        raise CalibrationError(f"no frames could be read from {args.source[0]}: give a video, a folder of images or a "
                               f"camera index that delivers frames")
    options = SelectionOptions(min_corners=args.min_corners, min_views=args.min_views, max_views=args.max_views,
                               border_px=border_margin(args.refine) if args.border_margin is None else args.border_margin,
                               select_terms=not args.all_terms, weight_views=not args.equal_weights)
    result = calibrate(frames, board, size, args.model, options, fix_k3=args.fix_k3)
    files = {out: calibration_text(result, board, args.detector, out.name, networks_of(args))}
    if report is not None:
        try:
            import matplotlib  # noqa: F401 - the report's figures need it: the eval extra
        except ImportError as exc:
            print(f"no report ({exc}): pip install 'deepcharuco[eval]' for it", file=sys.stderr)
            report = None
        else:
            from deepcharuco.calibration.report import report_html

            report.parent.mkdir(parents=True, exist_ok=True)
            files[report] = report_html(result, board, title=f"Calibration of {source.stem} ({args.detector} detector)",
                                        command="python -m deepcharuco.calibrate " + " ".join(args.argv))
    files.update(export_outputs(args, export_folder(out, False), ExportRig.single(result.camera, out.stem)))
    write_together(files)  # both or neither: a full disk leaves the previous files as they were
    K, std = result.camera.K, result.std
    deviation = (lambda name: f" +- {std[name]:.2f}" if name in std else "")  # noqa: E731
    print(f"{len(result.views)} views of {result.frames} frames ({sum(d.corners > 0 for d in result.decisions)} with "
          f"corners): RMS {result.rms:.3f} px, fx {K[0, 0]:.2f}{deviation('fx')}, fy {K[1, 1]:.2f}{deviation('fy')}, "
          f"cx {K[0, 2]:.2f}{deviation('cx')}, cy {K[1, 2]:.2f}{deviation('cy')}, corner sigma "
          f"{result.corner_sigma:.3f} px, dist "
          f"{np.array2string(result.camera.dist, precision=4, separator=' ')} -> {out}"
          + (f", {report}" if report is not None else ""))
    for note in result.notes:
        print(f"note: {note}", file=sys.stderr)
    return result


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m deepcharuco.calibrate", formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description="Calibrate a camera from a video, a folder of images or a live camera showing a ChArUco board: "
                    "detect the board in every frame, select views covering the image and a range of tilts, solve "
                    "with OpenCV, reject outliers, re-solve; write an OpenCV FileStorage camera file and an HTML report.")
    parser.add_argument("source", nargs="+",
                        help="video file, folder of images, or camera index (0, 1, ...); several: the synchronised "
                             "cameras of a rig (frame n of each shows one instant), calibrated together into --out/")
    parser.add_argument("--board", action="append", default=None,
                        help="board description (.yaml/.json); default: the paper's 5x5 DICT_5X5_50 board. A rig may "
                             "give several (--board a.yaml --board b.yaml: boards of other dictionaries or "
                             "first_marker_id, each seen by some cameras at once)")
    parser.add_argument("--out", default=None,
                        help="camera file to write (OpenCV FileStorage YAML; default camera.yaml), or with several "
                             "sources the rig's folder (default rig/): <source name>.yaml per camera, rig.toml, "
                             "rig_report.html")
    parser.add_argument("--camera", action="append", default=None, metavar="FILE",
                        help="a rig: one per source, in order, the camera file whose intrinsics are held fixed, or - "
                             "to solve that camera's (default: every camera's intrinsics are solved)")
    parser.add_argument("--sync-offsets", type=int, nargs="+", default=None, metavar="N",
                        help="a rig: one per source, the frames to skip at its start so that the sources line up "
                             "(a video started 3 frames before the others: 3; frame n + N_i of source i shows the "
                             "same instant as frame n + N_j of source j); default: all 0")
    parser.add_argument("--sync", choices=["auto", "frames"], default=None,
                        help="a rig: how its sources line up in time. auto: each source's delay to the first from the "
                             "board's motion (how fast it turns and moves, which every camera sees alike), to a "
                             "fraction of a frame, reported with its uncertainty, each frame then paired with the "
                             "nearest instant (docs/calibration.md); frames: frame n of each source is one instant. "
                             "Default: frames, or auto where the sources differ in length or their views at frame n "
                             "disagree on where the cameras stand (the output says so and by how much)")
    parser.add_argument("--timestamps", default=None, metavar="CSV",
                        help="a rig whose cameras ran at their own times: a CSV with source,frame,time_s per frame "
                             "(source: a source's name, e.g. cam_0, or its position 0, 1, ...); the instants are the "
                             "first source's frames, another's frame joins the one nearest in time within half a "
                             "frame interval")
    parser.add_argument("--origin", choices=["camera", "board"], default="camera",
                        help="a rig's frame: the first camera's (camera), or the board's at the instant the most "
                             "cameras saw it (board; --origin-instant chooses the instant)")
    parser.add_argument("--origin-instant", type=int, default=None, metavar="N",
                        help="--origin board: the board's frame at instant N (frame N of the first source)")
    parser.add_argument("--detector", choices=DETECTORS, default="deep",
                        help="corner detector. deep (the default), chosen by measurement (docs/calibration.md, "
                             "rendered calibration sequences of 5 cameras): fx/fy within 0.3 %% and cx/cy within "
                             "1 px on 5 of 5 in good light (OpenCV + cornerSubPix on none), RMS 0.46-0.73x OpenCV's, "
                             "and a calibration at 1 lux and under shake where OpenCV's corners give none. hybrid: "
                             "OpenCV's corners where they fit the board, the deep ones elsewhere; opencv: OpenCV alone")
    parser.add_argument("--model", choices=MODELS, default="pinhole",
                        help="pinhole: k1 k2 p1 p2 k3; rational: + k4 k5 k6; fisheye: OpenCV's fisheye k1..k4 (wide "
                             "lenses up to ~180 degrees). A rig: the model of every camera it solves; a --camera "
                             "file's model is its camera's, so a rig may mix fisheye and pinhole cameras")
    parser.add_argument("--fix-k3", action="store_true",
                        help="keep k3 at 0 (pinhole/rational): for few views or a small board, where a free k3 bends "
                             "the model beyond the corners seen")
    parser.add_argument("--all-terms", action="store_true",
                        help="solve the tangential terms p1 p2 always; by default (pinhole/rational, 10 views or more) "
                             "they are held at 0 when that predicts held-out views as well (5-fold cross-validation "
                             "over the views): free p1 p2 trade against the principal point and add noise to it")
    parser.add_argument("--equal-weights", action="store_true",
                        help="weigh every view alike (OpenCV's solution); by default (pinhole/rational, 10 views or "
                             f"more) a view whose residuals spread more than {VIEW_WEIGHT_SPREAD:g} x the median view's counts less in "
                             "that direction: motion-blurred views of a shaken video no longer count as much as sharp ones")
    parser.add_argument("--refine", choices=["subpix", "none", "refinenet"], default=None,
                        help="corner refinement (default: subpix for opencv, refinenet for deep and hybrid)")
    parser.add_argument("--weights", default=None, help="--detector deep: weights (default: the shipped ones)")
    parser.add_argument("--network", choices=NETWORKS, default=None,
                        help="deep/hybrid: auto (the default with the shipped weights): the distilled fast networks "
                             "first, the lite ones in every frame they find too little in; fast: the lite networks "
                             "only in a dim frame the fast ones find nothing in; lite (the default with --weights): "
                             "the lite networks alone (docs/detector.md); auto and fast not with --weights")
    parser.add_argument("--report", default=None, help="HTML report to write (default: <out>_report.html)")
    parser.add_argument("--no-report", action="store_true", help="write the camera file only")
    parser.add_argument("--force", action="store_true",
                        help="overwrite --out (or the report) even where it is not a camera file (report)")
    parser.add_argument("--max-views", type=int, default=80, help="at most this many views are calibrated")
    parser.add_argument("--min-views", type=int, default=6, help="fewer usable views is an error")
    parser.add_argument("--min-corners", type=int, default=6, help="a view needs this many corners")
    parser.add_argument("--border-margin", type=float, default=None,
                        help="corners nearer the image's border than this (px) are not used (default: 12 for "
                             "--refine refinenet, whose 24 px patch would reach past the border, else 0)")
    parser.add_argument("--step", type=int, default=1, help="look at every n-th frame only")
    parser.add_argument("--jobs", type=int, default=1,
                        help="worker processes that detect frames side by side, of one camera or of a rig's (up to "
                             "~jobs x the frames a second where the cores are there; the same detections)")
    parser.add_argument("--max-frames", type=int, default=None, help="stop after this many frames (a camera: required)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_export_options(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = argv
    args.refine = args.refine or ("subpix" if args.detector == "opencv" else "refinenet")
    problems = [f"--{name.replace('_', '-')} must be >= {low}, got {getattr(args, name)}"
                for name, low in (("max_views", 4), ("min_views", 4), ("min_corners", 4), ("step", 1), ("jobs", 1))
                if getattr(args, name) < low]
    if args.max_frames is not None and args.max_frames < 1:
        problems.append(f"--max-frames must be >= 1, got {args.max_frames}")
    if args.border_margin is not None and args.border_margin < 0:
        problems.append(f"--border-margin must be >= 0, got {args.border_margin:g}")
    if any(s.isdigit() and not Path(s).exists() for s in args.source) and args.max_frames is None:
        problems.append("a live camera needs --max-frames (how many frames to capture)")
    rig = len(args.source) > 1
    if not rig and (args.camera or args.sync_offsets or args.timestamps or args.sync):
        option = ("--camera" if args.camera else "--sync-offsets" if args.sync_offsets else "--timestamps"
                  if args.timestamps else "--sync")
        problems.append(f"{option} is for a rig (two sources or more); one camera's intrinsics are what calibrate "
                        f"solves")
    if args.origin_instant is not None and args.origin != "board":
        problems.append("--origin-instant is for --origin board")
    if args.sync_offsets and args.timestamps:
        problems.append("give --sync-offsets or --timestamps, not both (timestamps line the sources up themselves)")
    if args.sync and (args.sync_offsets or args.timestamps):
        given = "--sync-offsets" if args.sync_offsets else "--timestamps"
        problems.append(f"give --sync {args.sync} or {given}, not both ({given} lines the sources up by hand)")
    if rig and args.camera and len(args.camera) != len(args.source):
        problems.append(f"--camera given {len(args.camera)} times for {len(args.source)} sources: give one per source "
                        f"(- for a camera to solve)")
    if rig and args.sync_offsets and len(args.sync_offsets) != len(args.source):
        problems.append(f"--sync-offsets has {len(args.sync_offsets)} values for {len(args.source)} sources: give one "
                        f"per source")
    if args.sync_offsets and min(args.sync_offsets) < 0:
        problems.append("--sync-offsets are frames to skip at each source's start: >= 0")
    if not rig and args.board and len(args.board) > 1:
        problems.append("several --board files are for a rig (two sources or more); one camera calibrates from one "
                        "board")
    args.out = args.out or ("rig" if rig else "camera.yaml")
    if args.fix_k3 and args.model == "fisheye":
        problems.append("--fix-k3 is for the pinhole and rational models (fisheye has k1..k4)")
    if args.all_terms and args.model == "fisheye":
        problems.append("--all-terms is for the pinhole and rational models (fisheye has no p1 p2 to hold; it solves "
                        "k1..k4 always)")
    if args.max_views < args.min_views:
        problems.append(f"--max-views ({args.max_views}) must be >= --min-views ({args.min_views})")
    problems += export_problems(args, rig)
    if problems:
        parser.error("; ".join(problems))
    def body() -> None:
        try:
            args.network = args.network or default_network(args.weights)
            network_weights(args.network, args.weights)  # a conflict with --weights: refused here
            if rig:
                from deepcharuco.cli.calibrate_rig import run_rig

                boards = [load_board(path) for path in args.board] if args.board else [BoardSpec()]
                for j, board in enumerate(boards):
                    for i in range(j):
                        if boards[i].same_layout(board):
                            raise DeepCharucoError(
                                f"--board {args.board[i]} and --board {args.board[j]} are one board (the same markers "
                                f"in the same layout): give it once (each view of it would count twice, and the rig "
                                f"would look more certain than it is)")
                check_boards_apart(boards, [f"--board {path}" for path in args.board or ["(default)"]])
                run_rig(args, boards, [make_detector(args.detector, board, args.refine, args.weights,
                                                     network=args.network)
                                       for board in boards])
            else:
                run(args)
        except KeyboardInterrupt:  # Ctrl-C while detecting or solving: the files are written last, whole or not at all
            raise KeyboardInterrupt(f"nothing written ({args.out} is as it was); rerun to calibrate") from None

    return run_command(body)  # Ctrl-C: one line "stopped: ...", exit code 130


if __name__ == "__main__":
    sys.exit(main())
