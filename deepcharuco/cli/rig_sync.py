"""A rig's sources lined up in time by the board's motion (``calibrate a.mp4 b.mp4 ... --sync auto``).

`deepcharuco.cli.calibrate_rig` detects every frame of every source with its own frame number; here each source's
delay to the first is estimated (`deepcharuco.calibration.time_sync.align`, under each camera's starting intrinsics)
and the frames are renumbered as instants: each source's frame k is taken at ``k x interval - delay`` on the first
source's clock and joins the first source's frame nearest in time (within half a frame interval,
`deepcharuco.cli.calibrate_rig.instants_by_time`). The sub-frame part of a delay is reported, not interpolated:
a frame is paired with the nearest instant, so up to half a frame of the delay remains in the pairs.

The same alignment is the fallback without ``--sync``: when the sources have different lengths, or when their
views at frame n disagree on where the cameras stand (`worst_spread`, the check `calibrate_rig` refuses by), they
are aligned automatically and the output says so and by how much.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.calibration.rig_init import MAX_PAIR_SPREAD_DEG, MIN_SHARED_VIEWS, relative_poses, view_poses
from deepcharuco.calibration.rig_model import RigView
from deepcharuco.calibration.time_sync import Alignment, SyncError, align
from deepcharuco.calibration.views import FrameDetection
from deepcharuco.cli.sources import Source
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
