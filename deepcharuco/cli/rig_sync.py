"""A rig's sources lined up in time: by the board's motion (``calibrate a.mp4 b.mp4 ... --sync auto``), or by
their frames' times (``--timestamps``: `read_timestamps`, `instants_by_time`).

`deepcharuco.cli.calibrate_rig` detects every frame of every source with its own frame number; here each source's
delay to the first is estimated (`deepcharuco.calibration.time_sync.align`, under each camera's starting intrinsics)
and the frames are renumbered as instants: each source's frame k is taken at ``k x interval - delay`` on the first
source's clock and joins the first source's frame nearest in time (within half a frame interval,
`instants_by_time`). The sub-frame part of a delay is reported, not interpolated:
a frame is paired with the nearest instant, so up to half a frame of the delay remains in the pairs.

The same alignment is the fallback without ``--sync``: when the sources have different lengths, or when their
views at frame n disagree on where the cameras stand (`worst_spread`, the check `calibrate_rig` refuses by), they
are aligned automatically and the output says so and by how much.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.calibration.rig_init import (
    MAX_PAIR_SPREAD_DEG,
    MIN_SHARED_VIEWS,
    relative_poses,
    view_poses,
)
from deepcharuco.calibration.rig_model import RigError, RigView
from deepcharuco.calibration.time_sync import Alignment, SyncError, align
from deepcharuco.calibration.views import FrameDetection
from deepcharuco.cli.sources import Source
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.geometry.camera import Camera

DEFAULT_FPS = 30.0  # a folder of images has no frame rate: it is taken at the videos' (the first's), else this


def frame_intervals(sources: list[Source]) -> list[float]:
    """Each source's frame interval (s): a video's from its frame rate; a folder's is the first video's (or
    1 / `DEFAULT_FPS`: with folders alone only the delays in frames mean anything)."""
    rates = [s.fps for s in sources if s.kind == "video" and s.fps > 0]
    fallback = rates[0] if rates else DEFAULT_FPS
    return [1.0 / (s.fps if s.kind == "video" and s.fps > 0 else fallback) for s in sources]


def check_recorded(sources: list[Source]) -> None:
    """`SyncError` for a live camera: the frames must be recorded (a video or a folder) to be read whole first."""
    for source in sources:
        if source.kind not in ("video", "images") or not source.total:
            raise SyncError(f"--sync auto needs recorded sources (videos or folders of images), but {source.stem} is "
                            f"a {source.kind}: record it first, or give --sync-offsets")


def worst_spread(detections: list[list[list[FrameDetection]]], boards: list[BoardSpec], cameras: list[Camera],
                 min_corners: int) -> tuple[float, tuple[int, int] | None]:
    """The largest disagreement (median degrees) of a pair of cameras with itself over the instants both saw a
    board at (`deepcharuco.calibration.rig_init.relative_poses`, ``detections[c][b]`` indexed by instant), and
    the pair; (0, None) where no pair shares `MIN_SHARED_VIEWS` instants."""
    views = [RigView(c, f.index, f.ids, f.corners, board=b) for c, per_board in enumerate(detections)
             for b, frames in enumerate(per_board) for f in frames if len(f.ids)]
    poses, _, _ = view_poses(views, boards, cameras, min_corners)
    pairs = relative_poses(poses, len(cameras))
    counted = {key: pair.spread_deg for key, pair in pairs.items() if pair.count >= MIN_SHARED_VIEWS}
    if not counted:
        return 0.0, None
    key = max(counted, key=counted.get)
    return counted[key], key


def disagree(spread: float) -> bool:
    """True where the views disagree as `deepcharuco.calibration.rig_init.check_synchronised` refuses."""
    return spread > MAX_PAIR_SPREAD_DEG


def align_sources(detections: list[list[list[FrameDetection]]], boards: list[BoardSpec], cameras: list[Camera],
                  intervals: list[float], names: list[str], min_corners: int) -> Alignment:
    """Each source's delay to the first from ``detections[c][b]`` (every frame, indexed by its number), followed
    on the board seen in the most frames with a pose-worthy view."""
    counts = [sum(len(f.ids) >= min_corners for per_board in detections for f in per_board[b])
              for b in range(len(boards))]
    b = int(np.argmax(counts))
    return align([per_board[b] for per_board in detections], boards[b], cameras, intervals, names,
                 min_corners=min_corners, board_index=b)


def aligned_times(detections: list[list[list[FrameDetection]]], alignment: Alignment) -> list[dict[int, float]]:
    """Per source, {frame: time on the first source's clock (s)}: frame k at ``k x interval - delay``."""
    times = []
    for per_board, delay in zip(detections, alignment.delays):
        frames = sorted({f.index for frames in per_board for f in frames})
        times.append({k: k * delay.interval - delay.delay_s for k in frames})
    return times


def renumbered(detections: list[list[list[FrameDetection]]], mapping: list[dict[int, int]], step: int = 1
               ) -> list[list[list[FrameDetection]]]:
    """``detections`` with each frame's index replaced by its instant (``mapping[c]``: {frame: instant}); frames
    that join no instant, and instants not a multiple of ``step``, left out."""
    out = []
    for per_board, table in zip(detections, mapping):
        out.append([[dataclasses.replace(f, index=table[f.index]) for f in frames
                     if f.index in table and table[f.index] % step == 0] for frames in per_board])
    return out


def describe(alignment: Alignment, why: str, folders: bool) -> str:
    """What the command prints: that it aligned the sources automatically, why, and by how much."""
    parts = []
    for name, d in zip(alignment.names[1:], alignment.delays[1:]):
        seconds = "" if folders else f", {1000 * d.delay_s:+.0f} +- {1000 * d.std_s:.0f} ms"
        parts.append(f"{name} {d.frames:+.2f} +- {d.std_frames:.2f} frames{seconds} (correlation {d.peak:.2f}, "
                     f"next peak {d.second:.2f})")
    return (f"aligned in time automatically ({why}) from the board's motion; each source's delay to "
            f"{alignment.names[0]} (frames to skip at its start; each frame paired with the nearest instant): "
            + "; ".join(parts))


def read_timestamps(path: str | Path, names: list[str], totals: list[int | None] | None = None
                    ) -> list[dict[int, float]]:
    """Each source's {frame: time (s)} from a CSV with the columns ``source,frame,time_s`` (``source``: the source's
    name, e.g. ``cam_0`` for cam_0.mp4, or its position 0, 1, ...). Refused, naming the line: a time that is not
    finite, a negative frame or one past its source's ``totals`` (frames, where known), one frame given twice at
    different times; and a source without any row, or whose times do not increase with its frame numbers."""
    import csv

    try:
        with open(path, newline="", encoding="utf-8") as handle:
            rows = list(csv.DictReader(handle))
    except OSError as error:
        raise DeepCharucoError(f"--timestamps {path}: cannot read it ({error.strerror or error})") from None
    except (UnicodeDecodeError, csv.Error) as error:
        raise DeepCharucoError(f"--timestamps {path} is not a text CSV ({type(error).__name__} at byte "
                               f"{getattr(error, 'start', '?')}): give a UTF-8 CSV with the header source,frame,time_s"
                               ) from None
    if not rows or not {"source", "frame", "time_s"} <= set(rows[0]):
        raise DeepCharucoError(f"--timestamps {path} needs a header source,frame,time_s and one row per frame")
    times: list[dict[int, float]] = [{} for _ in names]
    for line, row in enumerate(rows, start=2):
        key = row["source"].strip()
        camera = names.index(key) if key in names else int(key) if key.isdigit() and int(key) < len(names) else None
        if camera is None:
            raise DeepCharucoError(f"--timestamps {path} line {line}: source {key!r} is none of {', '.join(names)} "
                                   f"(or 0..{len(names) - 1})")
        try:
            frame, time = int(row["frame"]), float(row["time_s"])
        except (ValueError, TypeError):
            raise DeepCharucoError(f"--timestamps {path} line {line}: frame and time_s must be numbers") from None
        where = f"--timestamps {path} line {line}"
        if not math.isfinite(time):
            raise DeepCharucoError(f"{where}: time_s {row['time_s'].strip()} is not a time: give seconds")
        if frame < 0 or (totals and totals[camera] and frame >= totals[camera]):
            raise DeepCharucoError(f"{where}: frame {frame} of {names[camera]}, whose frames are numbered 0.."
                                   f"{(totals[camera] - 1) if totals and totals[camera] else 'N'}: give frame numbers "
                                   f"from 0 (a folder's: its images' places in name order)")
        if frame in times[camera] and times[camera][frame] != time:
            raise DeepCharucoError(f"{where}: frame {frame} of {names[camera]} again, at {time:g} s (before: "
                                   f"{times[camera][frame]:g} s): give each frame once")
        times[camera][frame] = time
    for name, table in zip(names, times):
        if not table:
            raise DeepCharucoError(f"--timestamps {path} has no row for {name}: give every source's frame times")
        ordered = [table[frame] for frame in sorted(table)]
        if len(ordered) > 1 and not all(b > a for a, b in zip(ordered, ordered[1:])):
            raise DeepCharucoError(f"--timestamps {path}: {name}'s times do not increase with its frame numbers "
                                   f"(two frames at one time, or out of order): give each frame the time it was taken")
    return times


def instants_by_time(times: list[dict[int, float]]) -> list[dict[int, int]]:
    """Per source, {frame: instant}: the instants are the first source's frames, and another source's frame belongs
    to the instant nearest in time when within half of the first source's median frame interval (the nearer of two
    frames that would share one)."""
    reference = sorted(times[0].items(), key=lambda item: item[1])
    frames0 = np.array([frame for frame, _ in reference])
    times0 = np.array([t for _, t in reference])
    tolerance = 0.5 * float(np.median(np.diff(times0))) if len(times0) > 1 else math.inf
    mapping: list[dict[int, int]] = [{int(f): int(f) for f in frames0}]
    for table in times[1:]:
        best: dict[int, tuple[float, int]] = {}
        for frame, t in table.items():
            k = int(np.clip(np.searchsorted(times0, t), 1, len(times0) - 1)) if len(times0) > 1 else 0
            k = k - 1 if k > 0 and abs(times0[k - 1] - t) <= abs(times0[k] - t) else k
            gap = abs(times0[k] - t)
            if gap <= tolerance and (frames0[k] not in best or gap < best[frames0[k]][0]):
                best[int(frames0[k])] = (gap, frame)
        mapping.append({frame: instant for instant, (_, frame) in best.items()})
    return mapping


def check_overlap(times: list[dict[int, float]], mapping: list[dict[int, int]], names: list[str]) -> None:
    """`RigError` naming a source none of whose frames joins an instant of the first (`instants_by_time`): its clock
    never overlaps the first's."""
    for c in range(1, len(names)):
        if not mapping[c]:
            spans = [f"{names[k]} {min(times[k].values()):g}..{max(times[k].values()):g} s" for k in (0, c)]
            raise RigError(f"--timestamps: no frame of {names[c]} was taken within half a frame interval of one of "
                           f"{names[0]}'s ({', '.join(spans)}): give both sources' times on one clock")
