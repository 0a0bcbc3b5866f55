"""``python -m deepcharuco.calibrate cam0.mp4 cam1.mp4 ... --out rig/``: a rig of cameras from synchronised sources.

Every source is read frame by frame in step (frame n of each, after its ``--sync-offsets``, is one instant; with
``--timestamps``, the instants are the first source's frames and the others' frames nearest in time join them; with
``--sync auto``, and without ``--sync`` where the sources differ in length or their views at frame n disagree, every
frame of each is read and the sources are lined up by the board's motion, `deepcharuco.cli.rig_sync`) and the board
detected in each frame (one progress bar over the instants). Each camera's intrinsics start from its
own single-camera calibration (`deepcharuco.calibration.intrinsics.calibrate`, as ``calibrate`` does for one camera) or
are held at a given ``--camera`` file's; then `deepcharuco.calibration.rig.calibrate_rig` places the cameras and
bundle-adjusts everything together. Writes into ``--out``: ``<source name>.yaml`` per camera, ``rig.toml`` and
``rig_report.html`` (`deepcharuco.calibration.rig_files`, `deepcharuco.calibration.rig_report`), all together and last: bad input
leaves nothing behind (one line, exit code 2).
"""

from __future__ import annotations

import argparse
import filecmp
import sys
from pathlib import Path

import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.calibration.intrinsics import calibrate
from deepcharuco.calibration.rig import calibrate_rig
from deepcharuco.calibration.rig_files import is_rig_toml, rig_camera_text, rig_toml
from deepcharuco.calibration.rig_model import RigError, RigResult, RigView, rotations_from_vectors
from deepcharuco.calibration.time_sync import SyncError
from deepcharuco.calibration.views import (CalibrationError, FrameDetection, SelectionOptions, border_margin,
                                           within_border)
from deepcharuco.cli.calibration_exports import export_outputs, refuse_foreign_exports
from deepcharuco.cli.calibration_frames import calibration_pool, detect_views, networks_of
from deepcharuco.cli.common import check_output_folder, four_term_note, no_empty_folders_on_failure
from deepcharuco.cli.rig_sync import (aligned_times, align_sources, check_overlap, check_recorded, describe, disagree,
                                      frame_intervals, instants_by_time, read_timestamps, renumbered, worst_spread)
from deepcharuco.cli.sources import Source, frame_numbers, open_source
from deepcharuco.core.errors import CameraFileError, DeepCharucoError
from deepcharuco.core.files import OutputLock, refuse_foreign, starts_with, write_together
from deepcharuco.core.image import to_gray_u8
from deepcharuco.detection.parallel import DetectorPool
from deepcharuco.geometry.camera import Camera, is_camera_file, read_camera

TOML_NAME, REPORT_NAME = "rig.toml", "rig_report.html"
REPORT_START = b"<!doctype html><html><head><meta charset='utf-8'><title>Rig calibration"


def source_names(sources: list[Source]) -> list[str]:
    """The cameras' names (their sources' stems); two sources of one name are refused."""
    names = [source.stem for source in sources]
    for name in names:
        if names.count(name) > 1:
            raise DeepCharucoError(f"two sources are named {name}: each camera's file is rig/<name>.yaml, so give "
                                   f"sources with different names (rename or link one)")
    return names


def refuse_one_source_twice(paths: list[str]) -> None:
    """Two of a rig's sources that are one recording (one file or folder under two names or links, or two files,
    or folders of files, with the same bytes) are refused: they would be two cameras standing in one place, every
    view counted twice."""
    def same_bytes(a: Path, b: Path) -> bool:
        if a.is_dir() != b.is_dir():
            return False
        if a.is_dir():
            listed = [sorted((p.name, p.stat().st_size) for p in folder.iterdir() if p.is_file()) for folder in (a, b)]
            return listed[0] == listed[1] and all(filecmp.cmp(a / name, b / name, shallow=False) for name, _ in listed[0])
        return a.stat().st_size == b.stat().st_size and filecmp.cmp(a, b, shallow=False)

    files = [(source, Path(source)) for source in paths if Path(source).exists()]
    for j, (name_j, path_j) in enumerate(files):
        for name_i, path_i in files[:j]:
            if path_i.samefile(path_j) or same_bytes(path_i, path_j):
                raise DeepCharucoError(f"{name_i} and {name_j} are one recording (the same file, folder or bytes): "
                                       f"a rig needs one source per camera; give each once")


def different_lengths(sources: list[Source]) -> str | None:
    """"name N, name M" of recorded sources (videos, folders) when their lengths differ, else None."""
    totals = [(s.stem, s.total) for s in sources if s.kind in ("video", "images") and s.total]
    if len({total for _, total in totals}) > 1:
        return ", ".join(f"{name} {total}" for name, total in totals)
    return None


def check_lengths(sources: list[Source], offsets: list[int] | None) -> None:
    """Videos (or folders of frames) of one rig recorded together have one length; with --sync frames (no
    --sync-offsets) other lengths are refused."""
    for source, offset in zip(sources, offsets or []):
        if source.total and offset >= source.total:
            raise RigError(f"--sync-offsets {offset} for {source.stem} skips every one of its {source.total} frames: "
                           f"give the frames to skip at its start, fewer than it has")
    listed = different_lengths(sources)
    if offsets is None and listed:
        raise RigError(f"the sources have different lengths ({listed} frames), so frame n of each need not show one "
                       f"instant: give --sync auto (line them up by the board's motion) or --sync-offsets (the frames "
                       f"to skip at each one's start so that they line up), or trim them to start and end together")


def detect_synchronised(sources: list[Source], detectors: list, offsets: list[int], *, step: int = 1,
                        quiet: bool = False, pool: DetectorPool | None = None
                        ) -> tuple[list[list[list[FrameDetection]]], list[tuple[int, int] | None]]:
    """``detections[c][b]``: camera c's `FrameDetection` of board b (``detectors[b]``'s) at every ``step``-th
    instant (the instant as its index), and each camera's frame size. Frame ``n + offsets[c]`` of source c is
    instant n, by the frames' numbers in their recordings (`deepcharuco.cli.sources.frame_numbers`): a frame a reader
    skipped (a damaged stretch of video, an unreadable image) leaves that camera out of its instant and shifts no
    other frame. Reading stops when the first source ends. ``pool``: a `DetectorPool` whose finders are these
    detectors (worker processes; default: these detectors in this process)."""
    def instants(source: Source, offset: int):
        for number, name, frame in frame_numbers(source):
            if number >= offset:
                yield number - offset, name, frame

    streams = [instants(source, offset) for source, offset in zip(sources, offsets)]
    totals = [s.total - o for s, o in zip(sources, offsets) if s.total]
    sizes: list[tuple[int, int] | None] = [None] * len(sources)

    def wanted():
        heads = [next(stream, None) for stream in streams]
        for c, head in enumerate(heads):
            if head is None:  # reading stops at the first source that ends: name the one that never began
                skipping = f" after the {offsets[c]} frames --sync-offsets skips" if offsets[c] else ""
                raise CalibrationError(f"no frames could be read from {sources[c].stem}{skipping}: give videos, "
                                       f"folders of images or camera indices that deliver frames")
        while all(head is not None for head in heads):
            instant = min(head[0] for head in heads)
            for c, head in enumerate(heads):
                if head[0] != instant:
                    continue  # this camera's frame of the instant could not be read
                if instant % step == 0:
                    gray = _checked_gray(c, head[1], head[2], sources[c], sizes)
                    yield (c, instant, str(head[1]), gray), gray
                heads[c] = next(streams[c], None)

    total = len(sources) * -(-min(totals) // step) if totals else None
    return detect_views(wanted(), detectors, len(sources), pool, total, quiet), sizes


def _checked_gray(camera: int, name: str, frame: np.ndarray, source: Source,
                  sizes: list[tuple[int, int] | None]) -> np.ndarray:
    """``camera``'s ``frame`` as uint8 grey; the camera's frame size is kept in ``sizes`` and another size refused."""
    gray = to_gray_u8(frame)
    size = (gray.shape[1], gray.shape[0])
    if sizes[camera] is None:
        sizes[camera] = size
    elif size != sizes[camera]:
        raise CalibrationError(f"{source.stem}: frame {name} is {size[0]}x{size[1]} but the first was "
                               f"{sizes[camera][0]}x{sizes[camera][1]}: one camera, one resolution")
    return gray


def detect_by_time(sources: list[Source], detectors: list, mapping: list[dict[int, int]], *, step: int = 1,
                   quiet: bool = False, pool: DetectorPool | None = None
                   ) -> tuple[list[list[list[FrameDetection]]], list[tuple[int, int] | None]]:
    """`detect_synchronised`'s result where the instants come from timestamps (`instants_by_time`): each source
    is read whole, and only its frames that belong to an instant (every ``step``-th) are detected."""
    sizes: list[tuple[int, int] | None] = [None] * len(sources)

    def wanted():
        for c, source in enumerate(sources):
            for frame_index, name, frame in frame_numbers(source):  # a frame skipped shifts no other
                instant = mapping[c].get(frame_index)
                if instant is not None and instant % step == 0:
                    gray = _checked_gray(c, name, frame, source, sizes)
                    yield (c, instant, str(name), gray), gray

    total = sum(1 for c in range(len(sources)) for instant in mapping[c].values() if instant % step == 0) or None
    return detect_views(wanted(), detectors, len(sources), pool, total, quiet), sizes


def starting_cameras(detections: list[list[list[FrameDetection]]], sizes: list[tuple[int, int]], names: list[str],
                     given: list[str | None], boards: list[BoardSpec], model: str, options: SelectionOptions,
                     fix_k3: bool) -> tuple[list[Camera], list[str | None], list[str], list[dict[str, float] | None],
                                            list[float | None]]:
    """Each camera's starting intrinsics (its single-camera calibration from the board it saw in the most frames),
    the distortion terms the rig solves for it (None: held as given), what to tell the user, and the starting
    intrinsics' standard deviations (`deepcharuco.calibration.rig`'s prior) and corner noise (px per axis; None where given)."""
    cameras, terms, notes, priors, noise = [], [], [], [], []
    for c, name in enumerate(names):
        if given[c] not in (None, "-"):
            try:
                camera = read_camera(given[c]).for_image_size(*sizes[c])
            except CameraFileError as error:
                raise CameraFileError(f"--camera {given[c]} ({name}): {error}") from None
            cameras.append(camera)
            terms.append(None)
            priors.append(None)
            noise.append(None)
            continue
        seen = [sum(len(f.ids) >= options.min_corners for f in frames) for frames in detections[c]]
        b = int(np.argmax(seen))
        try:
            single = calibrate(detections[c][b], boards[b], sizes[c], model, options, fix_k3=fix_k3)
        except CalibrationError as error:
            raise RigError(f"{name}: {error} (or give its intrinsics: --camera FILE for it)") from None
        cameras.append(single.camera)
        terms.append(single.terms)
        notes += [f"{name}: {note}" for note in single.notes]
        priors.append(dict(single.std))
        noise.append(single.corner_sigma)
    return cameras, terms, notes, priors, noise


def check_given_models(given: list[str | None] | None, model: str) -> None:
    """A given camera file's model is its camera's (held as given; the rig may mix models), ``--model`` the model of
    the cameras solved here: where every camera is given, a ``--model`` other than the default that some file
    disagrees with would change nothing, and is refused (`CameraFileError`) before any frame is read. So is a file
    the rig's solve cannot hold as it is (`held_as_given`)."""
    held = {path: held_as_given(path) for path in given or [] if path not in (None, "-")}
    if not given or any(path in (None, "-") for path in given) or model == "pinhole":
        return
    for path in given:
        camera = held[path]
        kind = "fisheye" if camera.model == "fisheye" else "rational" if camera.dist.size >= 8 else "pinhole"
        if kind != model:
            raise CameraFileError(f"--model {model} is the model of the cameras the rig solves, but every camera is "
                                  f"held at its --camera file and {path} is a {kind} camera: give - for a camera to "
                                  f"solve with --model {model}, or leave --model out")


def held_as_given(path: str) -> Camera:
    """The camera file ``path`` as the rig holds it, or `CameraFileError` where the rig's model (fx, fy, cx, cy and up
    to 8 distortion terms, `calibration.rig_model.INTRINSICS`) would drop part of it: a skew, or a 12- or
    14-coefficient model's thin-prism or tilt terms. They were dropped without a word, and the camera solved and
    written without them."""
    try:
        camera = read_camera(path)
    except CameraFileError as error:
        raise CameraFileError(f"--camera {path}: {error}") from None
    note = four_term_note(path, camera)
    if note:
        print(note, file=sys.stderr)
    if camera.model != "fisheye":
        beyond = np.flatnonzero(camera.dist[8:]) + 8
        if camera.K[0, 1] != 0 or len(beyond):
            what = f"a skew (camera_matrix[0][1] = {camera.K[0, 1]:g})" if camera.K[0, 1] != 0 else \
                f"distortion terms past the eighth ({len(camera.dist)} coefficients: thin prism or tilt)"
            raise CameraFileError(f"--camera {path} holds {what}, which a rig's cameras do not model: the camera "
                                  f"would be held without it; give a file of up to 8 coefficients and no skew, or - to "
                                  f"solve that camera here")
    return camera


def solve_rig(detections: list[list[list[FrameDetection]]], sizes: list[tuple[int, int]], names: list[str],
              boards: list[BoardSpec], options: SelectionOptions, *, model: str = "pinhole", fix_k3: bool = False,
              given: list[str | None] | None = None, weigh_rig_corners: bool = True, starts: tuple | None = None
              ) -> RigResult:
    """The rig from every camera's detections of every board (``detections[c][b]``: one `FrameDetection` per
    instant, its index the instant): starting intrinsics (`starting_cameras`), corners within
    ``options.border_px`` of the border left out, then `calibrate_rig`, which weighs corners by their covariances
    where ``options`` weighs one camera's and ``weigh_rig_corners``. ``starts``: `starting_cameras`' result where
    already computed (``--sync auto`` needs the intrinsics before the instants are known)."""
    cameras, terms, notes, priors, noise = starts or starting_cameras(
        detections, sizes, names, given or [None] * len(names), boards, model, options, fix_k3)
    views = []
    for c, per_board in enumerate(detections):
        for b, frames in enumerate(per_board):
            for frame in frames:
                kept = within_border(frame, sizes[c], options.border_px)
                if len(kept.ids):
                    views.append(RigView(c, frame.index, kept.ids, kept.corners, f"{names[c]} {frame.name}", b,
                                         kept.covariances))
    result = calibrate_rig(views, boards, cameras, names, terms, min_corners=options.min_corners, priors=priors,
                           own_noise=noise,
                           weigh_corners=options.weight_views and options.weight_corners and weigh_rig_corners)
    result.notes = notes + result.notes
    return result


def board_origin(result: RigResult, instant: int | None = None) -> tuple[tuple[int, int], RigResult]:
    """The rig in a board's frame at ``instant``, or (None) at the instant the most cameras saw it (the most corners
    breaking ties; of several boards, the first one's), and that (instant, board)."""
    seen: dict[tuple[int, int], list[int]] = {}
    for view in result.views:
        seen.setdefault(view.key, []).append(len(view.ids))
    if instant is not None:
        chosen = [key for key in seen if key[0] == instant]
        if not chosen:
            nearest = sorted({i for i, _ in seen}, key=lambda i: abs(i - instant))[:5]
            raise RigError(f"--origin-instant {instant}: no board pose was solved at that instant (no camera kept a "
                           f"view of it); instants near it that have one: {', '.join(map(str, sorted(nearest)))}")
        seen = {key: seen[key] for key in chosen}
    key = max(seen, key=lambda k: (-k[1], len(seen[k]), sum(seen[k]), -k[0]))
    rvec, tvec = result.board_poses[key]
    return key, result.reframed(rotations_from_vectors(rvec)[0], np.asarray(tvec, np.float64))


def run_rig(args: argparse.Namespace, boards: list[BoardSpec], detectors: list) -> RigResult:
    """The rig command (module docstring): ``boards`` and one detector each."""
    out = Path(args.out)
    if out.suffix.lower() in (".yaml", ".yml", ".xml", ".json") and not out.is_dir():
        raise DeepCharucoError(f"--out {out} names a file, but {len(args.source)} sources make a rig: give a folder, "
                               f"e.g. --out {out.with_suffix('')}/")
    check_output_folder(out)
    refuse_one_source_twice(args.source)
    check_given_models(args.camera, args.model)
    sources = [open_source(source, args.max_frames) for source in args.source]
    names = source_names(sources)
    targets = [out / f"{name}.yaml" for name in names] + [out / TOML_NAME] + ([] if args.no_report else [out / REPORT_NAME])
    for path in targets[:len(names)]:
        refuse_foreign(path, is_camera_file, "camera file", args.force)
    refuse_foreign(out / TOML_NAME, is_rig_toml, "rig file", args.force)
    if not args.no_report:
        refuse_foreign(out / REPORT_NAME, starts_with(REPORT_START), "rig report", args.force)
    refuse_foreign_exports(args, out, names)
    mapping = None  # with --timestamps: per source, {frame: instant}
    auto = None  # why the sources are aligned automatically (rig_sync), or None
    listed = different_lengths(sources)
    if args.timestamps is not None:
        times = read_timestamps(args.timestamps, names, [s.total if s.kind in ("video", "images") else None
                                                         for s in sources])
        mapping = instants_by_time(times)
        check_overlap(times, mapping, names)
    elif args.sync == "auto" or (args.sync is None and args.sync_offsets is None and listed):
        check_recorded(sources)
        auto = "--sync auto" if args.sync == "auto" else f"the sources have different lengths: {listed} frames"
    else:
        check_lengths(sources, args.sync_offsets)
    with no_empty_folders_on_failure(out):
        out.mkdir(parents=True, exist_ok=True)
        with OutputLock(out / TOML_NAME, "another calibrate"):
            return _rig_into(args, boards, detectors, out, sources, names, targets, mapping, auto)


def _rig_into(args, boards: list[BoardSpec], detectors: list, out: Path, sources: list[Source], names: list[str],
              targets: list[Path], mapping: list[dict[int, int]] | None, auto: str | None) -> RigResult:
    pool = calibration_pool(args.detector, boards, args.refine, args.weights, args.jobs, args.network)
    if auto is not None:  # every frame of every source, by its own number; instants once the delays are known
        every = [{k: k for k in range(source.total)} for source in sources]
        detections, sizes = detect_by_time(sources, detectors, every, quiet=args.quiet, pool=pool)
    elif mapping is None:
        offsets = args.sync_offsets or [0] * len(sources)
        detections, sizes = detect_synchronised(sources, detectors, offsets, step=args.step, quiet=args.quiet, pool=pool)
    else:
        detections, sizes = detect_by_time(sources, detectors, mapping, step=args.step, quiet=args.quiet, pool=pool)
    for source in sources:
        for line in source.problems():
            print(f"warning: {line}", file=sys.stderr)
    for name, size, source in zip(names, sizes, args.source):
        if size is None:
            raise CalibrationError(f"no frames could be read from {source} ({name}): give videos, folders of images "
                                   f"or camera indices that deliver frames")
    unseen = [name for name, per_board in zip(names, detections)
              if not any(len(f.ids) for frames in per_board for f in frames)]
    if unseen:
        raise RigError(f"the board was never found by {', '.join(unseen)} in {len(detections[0][0])} instants: check "
                       f"--board (squares, dictionary, an inverted print) and that the board is in that view, lit and "
                       f"in focus")
    margin = border_margin(args.refine) if args.border_margin is None else args.border_margin
    options = SelectionOptions(min_corners=args.min_corners, min_views=args.min_views, max_views=args.max_views,
                               border_px=margin, select_terms=not args.all_terms, weight_views=not args.equal_weights)
    starts, alignment = None, None
    if auto is None and mapping is None and args.sync is None and args.sync_offsets is None and args.step == 1:
        starts = starting_cameras(detections, sizes, names, args.camera or [None] * len(names), boards, args.model,
                                  options, args.fix_k3)
        spread, pair = worst_spread(detections, boards, starts[0], options.min_corners)
        if disagree(spread) and pair is not None and all(s.kind in ("video", "images") and s.total for s in sources):
            auto = (f"cameras {names[pair[0]]} and {names[pair[1]]} disagree on where they stand from one frame to "
                    f"the next by {spread:.1f} degrees")
    if auto is not None:
        starts = starts or starting_cameras(detections, sizes, names, args.camera or [None] * len(names), boards,
                                            args.model, options, args.fix_k3)
        try:
            alignment = align_sources(detections, boards, starts[0], frame_intervals(sources), names,
                                      options.min_corners)
        except SyncError as error:
            listed = different_lengths(sources)
            if listed is None or not all(source.kind == "images" for source in sources):
                raise
            # Folders of stills of different lengths: most often an image missing from one of them, which no motion
            # can line up; say that first.
            raise SyncError(f"the folders hold different numbers of images ({listed}), so their images cannot be "
                            f"paired by their places in the sorted listings, and lining them up by the board's motion "
                            f"failed: {error}. Give each folder the same instants (remove the images of an instant one "
                            f"camera lacks), or --timestamps") from None
        times = aligned_times(detections, alignment)
        mapping = instants_by_time(times)
        check_overlap(times, mapping, names)
        detections = renumbered(detections, mapping, args.step)
        print(describe(alignment, auto, all(s.kind == "images" for s in sources)))
    if args.origin == "board" and args.origin_instant is not None:
        seen = sorted({f.index for per_board in detections for frames in per_board for f in frames if len(f.ids)})
        if args.origin_instant not in seen:
            nearest = sorted(sorted(seen, key=lambda i: abs(i - args.origin_instant))[:5])
            raise RigError(f"--origin-instant {args.origin_instant}: no camera found the board at that instant (of "
                           f"{len(detections[0][0])} read); instants near it where one did: "
                           f"{', '.join(map(str, nearest))}")
    result = solve_rig(detections, sizes, names, boards, options, model=args.model, fix_k3=args.fix_k3,
                       given=args.camera, starts=starts)
    frame = f"camera {names[0]}'s"
    if args.origin == "board":
        (instant, board_index), result = board_origin(result, args.origin_instant)
        frame = f"the board's at instant {instant}" if len(boards) == 1 else \
            f"board {Path(args.board[board_index]).stem}'s at instant {instant}"
    files = {path: rig_camera_text(result, c, boards, args.detector, frame, path.name, networks_of(args))
             for c, path in enumerate(targets[:len(names)])}
    files[out / TOML_NAME] = rig_toml(result, frame)
    if not args.no_report:
        try:
            import matplotlib  # noqa: F401 - the report's figures need it: the eval extra
        except ImportError as exc:
            print(f"no report ({exc}): pip install 'deepcharuco[eval]' for it", file=sys.stderr)
        else:
            from deepcharuco.calibration.rig_report import report_html

            files[out / REPORT_NAME] = report_html(
                result, boards, frame, title=f"Rig calibration of {', '.join(names)} ({args.detector} detector)",
                command="python -m deepcharuco.calibrate " + " ".join(args.argv), alignment=alignment)
    files.update(export_outputs(args, out, result))
    write_together(files)
    print(f"{len(names)} cameras, {len({i for i, _ in result.board_poses})} instants, {len(result.views)} views: RMS {result.rms:.3f} px"
          f" -> {out}/")
    for c, name in enumerate(names):
        K, std, centre = result.cameras[c].K, result.std[c], result.centre(c)
        deviation = (lambda key, scale=1.0: f" +- {scale * std[key]:.2f}" if key in std else "")  # noqa: E731
        print(f"  {name}: {result.camera_views(c)} views, RMS {result.camera_rms(c):.3f} px, fx {K[0, 0]:.1f}"
              f"{deviation('fx')} fy {K[1, 1]:.1f}{deviation('fy')} cx {K[0, 2]:.1f}{deviation('cx')} cy "
              f"{K[1, 2]:.1f}{deviation('cy')}, centre ({centre[0]:+.3f}, {centre[1]:+.3f}, {centre[2]:+.3f}) m"
              + (f" +- {1000 * max(std['tx'], std['ty'], std['tz']):.1f} mm, rotation +- {std['rotation_deg']:.2f} deg"
                 if "tx" in std else ""))
    pairs = ", ".join(f"{names[i]}-{names[j]} {n}" for (i, j), n in sorted(result.shared.items()))
    print(f"  shared instants: {pairs}")
    for note in result.notes:
        print(f"note: {note}", file=sys.stderr)
    return result
