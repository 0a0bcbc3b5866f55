"""A rig's sources lined up in time from the board's own motion (``calibrate --sync auto``).

Cameras started by hand (phones, action cameras, webcams) are offset by frames. Every camera of a still rig sees
one board move, and two quantities of that motion do not depend on the camera that sees it: how fast the board
turns (the angle between its orientations in two frames, divided by their interval: a rotation's angle is the
same in every camera's frame) and how fast its centre moves (a distance is the same in every frame). So:

1. `board_poses`: the board's pose in every frame of a source where enough corners were found (``cv2.solvePnP``
   under the camera's intrinsics: a given camera file or the source's own first calibration);
2. `motion_signal`: the board's rotation speed (deg/s) and centre speed (m/s) between every two consecutive
   frames of the source, at the pair's mid-time on the source's own clock (frame k at ``k x`` its frame interval);
3. `align`: each source's signal against the first's, normalised correlation (the mean of the channels' Pearson
   correlations over the instants both have, at least `MIN_OVERLAP`) at every whole-frame delay of that
   source, the best refined to a fraction of a frame by maximising the same correlation with the source's signal
   interpolated linearly between its samples (within a frame either side). Sources of other frame rates meet on
   the seconds of their clocks.

The delay's standard deviation is Gauss-Newton's for a delay fitted to the reference signal, scaled by the
residuals and inflated for their correlation from one sample to the next (an AR(1) process's variance factor
(1 + r) / (1 - r)). Refused with the reason (`SyncError`): a board that barely turns (`MIN_TURN_DEG`), too few
frame pairs or too little overlap (`MIN_OVERLAP`, `MIN_OVERLAP_SHARE`), a best correlation below `MIN_PEAK`, or a second peak
(outside the first's lobe) within `MAX_SECOND_PEAK` of it: an ambiguous motion.

Conventions: source c's delay ``d_c`` (seconds) says that what the first source shows at time T on its clock, c
shows at T + d_c on its own; ``d_c / interval_c`` frames is what ``--sync-offsets`` would skip at c's start (a
source started 3 frames before the first: d = 3 frames). The first source's delay is 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize_scalar

from deepcharuco.boards.board import BoardSpec
from deepcharuco.calibration.rig_init import usable, view_pose
from deepcharuco.calibration.rig_model import RigError, RigView, rotation_angle_deg
from deepcharuco.calibration.views import FrameDetection
from deepcharuco.geometry.camera import Camera

MIN_TURN_DEG = 10.0  # the board must turn at least this far over a source (a board held still gives no signal)
MIN_OVERLAP = 12  # frame pairs both signals have at a delay for its correlation to count
MIN_OVERLAP_SHARE = 0.5  # ... and at least this share of the fewer pairs of the two: a short stretch of smooth
# motion correlates well with many others
MIN_PEAK = 0.5  # the best correlation must reach this: below it the two sources' motions do not match
MAX_SECOND_PEAK = 0.85  # a second peak this close to the best (as a share of it) makes the delay ambiguous
SMOOTHING = 1.0  # the refinement smooths the signals by a Gaussian of this many samples (`MotionSignal.smoothed`)
MAX_POSE_PX = 4.0  # a frame whose PnP pose leaves a larger RMS is not used (a misdetection)


class SyncError(RigError):
    """Sources that cannot be lined up from the board's motion; the message says why and what to do."""


@dataclass
class MotionSignal:
    """One source's board motion: ``values[k]`` (rotation deg/s, centre m/s) between frames k and k + 1 (NaN
    where either frame has no pose), at time ``(k + 0.5) * interval`` s on the source's clock."""

    values: np.ndarray  # (K, 2)
    interval: float  # seconds between frames
    turn_deg: float  # the largest angle between the board's orientation in a frame and in its first posed frame
    poses: int  # frames with a pose

    def smoothed(self, sigma: float = 1.0) -> MotionSignal:
        """The signal smoothed by a Gaussian of ``sigma`` samples over the samples it has (gaps stay NaN):
        interpolating noisy samples averages their noise, least half-way between them, which pulls a
        correlation's peak toward half frames; noise already averaged over neighbours is hardly changed."""
        radius = int(math.ceil(3 * sigma))
        kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
        finite = np.isfinite(self.values)
        filled = np.where(finite, self.values, 0.0)
        total = np.stack([np.convolve(filled[:, c], kernel, "same") for c in range(filled.shape[1])], 1)
        weight = np.stack([np.convolve(finite[:, c].astype(float), kernel, "same") for c in range(filled.shape[1])], 1)
        values = np.where(finite, total / np.maximum(weight, 1e-12), np.nan)
        return MotionSignal(values, self.interval, self.turn_deg, self.poses)

    @property
    def pairs(self) -> int:
        """Frame pairs that carry the signal."""
        return int(np.isfinite(self.values[:, 0]).sum())

    def at(self, times: np.ndarray) -> np.ndarray:
        """(len(times), 2) the signal at ``times`` (s, this source's clock) interpolated between its samples:
        Catmull-Rom cubic where the four samples around a time are there (linear interpolation smooths the
        signal between samples, which pulls a correlation's peak toward whole frames), linear where only the two
        beside it are, NaN otherwise."""
        position = times / self.interval - 0.5
        lower = np.floor(position + 1e-6).astype(np.int64)
        u = np.clip(position - lower, 0.0, 1.0)[:, None]
        n = len(self.values)

        def sample(k: np.ndarray) -> np.ndarray:
            inside = ((k >= 0) & (k < n))[:, None]
            return np.where(inside, self.values[np.clip(k, 0, n - 1)], np.nan)

        around = [sample(lower + d) for d in (-1, 0, 1, 2)]
        weights = [0.5 * (-u ** 3 + 2 * u ** 2 - u), 0.5 * (3 * u ** 3 - 5 * u ** 2 + 2), 0.5 * (-3 * u ** 3 + 4 * u ** 2 + u),
                   0.5 * (u ** 3 - u ** 2)]
        exact = u < 1e-6  # on a sample: its value alone (its neighbours may be missing)
        cubic = sum(w * v for w, v in zip(weights, around))
        linear = (1 - u) * around[1] + u * around[2]
        return np.where(exact, around[1], np.where(np.isfinite(cubic), cubic, linear))


@dataclass
class SourceDelay:
    """Source c's delay to the first (module docstring): ``delay_s``, its ``std_s``, the correlation at it
    (``peak``) and the best outside its lobe (``second``), the frame pairs both signals shared (``overlap``), and
    the whole-frame delays tried with their correlations (``lags`` in this source's frames, ``scores``)."""

    delay_s: float
    std_s: float
    interval: float
    peak: float
    second: float
    overlap: int
    lags: np.ndarray = field(default_factory=lambda: np.zeros(0))
    scores: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def frames(self) -> float:
        """The delay in this source's frames."""
        return self.delay_s / self.interval

    @property
    def std_frames(self) -> float:
        return self.std_s / self.interval


@dataclass
class Alignment:
    """Every source's delay to the first (``delays[0]`` is 0) and the signals they were found from."""

    names: list[str]
    delays: list[SourceDelay]
    signals: list[MotionSignal]
    board: int = 0  # the board whose motion was followed

    def lines(self) -> list[str]:
        """One line per source after the first: its delay in frames and seconds, with their deviations."""
        return [f"{name} {d.frames:+.2f} +- {d.std_frames:.2f} frames ({1000 * d.delay_s:+.1f} ms; correlation "
                f"{d.peak:.2f}, next peak {d.second:.2f})" for name, d in zip(self.names[1:], self.delays[1:])]


def board_poses(frames: list[FrameDetection], board: BoardSpec, camera: Camera, min_corners: int = 6
                ) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """{frame index: (R (3, 3), t (3,))} the board's pose in every frame of ``frames`` with ``min_corners``
    corners not along a line whose PnP fit leaves at most `MAX_POSE_PX` RMS."""
    poses = {}
    for frame in frames:
        view = RigView(0, frame.index, frame.ids, frame.corners)
        if usable(view, board, min_corners) is None:
            R, t, rms = view_pose(view, board, camera)
            if rms <= MAX_POSE_PX and t[2] > 0:
                poses[frame.index] = (R, t)
    return poses


def motion_signal(poses: dict[int, tuple[np.ndarray, np.ndarray]], frames: int, interval: float,
                  centre: np.ndarray) -> MotionSignal:
    """The board's motion (`MotionSignal`) from its ``poses`` in a source of ``frames`` frames ``interval`` s
    apart; ``centre`` (3,) the board's centre in its own frame (m)."""
    values = np.full((max(frames - 1, 0), 2), np.nan)
    for k in range(len(values)):
        if k in poses and k + 1 in poses:
            (R_a, t_a), (R_b, t_b) = poses[k], poses[k + 1]
            values[k, 0] = rotation_angle_deg(R_b @ R_a.T) / interval
            values[k, 1] = np.linalg.norm((R_b @ centre + t_b) - (R_a @ centre + t_a)) / interval
    first = poses[min(poses)][0] if poses else np.eye(3)
    turn = max((rotation_angle_deg(R @ first.T) for R, _ in poses.values()), default=0.0)
    return MotionSignal(values, interval, turn, len(poses))


def correlation(reference: MotionSignal, other: MotionSignal, delay_s: float, within: np.ndarray | None = None
                ) -> tuple[float, int]:
    """The mean over channels of the Pearson correlation of ``reference`` at its samples' times T with
    ``other`` at T + ``delay_s`` (interpolated), and the samples both have (NaN below `MIN_OVERLAP`, or below
    `MIN_OVERLAP_SHARE` of the fewer frame pairs of the two); ``within``: only these of ``reference``'s samples."""
    times = (np.arange(len(reference.values)) + 0.5) * reference.interval
    a, b = reference.values, other.at(times + delay_s)
    both = np.isfinite(a).all(1) & np.isfinite(b).all(1) & (True if within is None else within)
    n = int(both.sum())
    if n < max(MIN_OVERLAP, MIN_OVERLAP_SHARE * min(reference.pairs, other.pairs)):
        return math.nan, n
    a, b = a[both], b[both]
    a, b = a - a.mean(0), b - b.mean(0)
    scale = np.sqrt((a * a).sum(0) * (b * b).sum(0))
    if np.any(scale <= 0):
        return math.nan, n
    return float(np.mean((a * b).sum(0) / scale)), n


def delay_std(reference: MotionSignal, other: MotionSignal, delay_s: float) -> float:
    """The delay's standard deviation (s): Gauss-Newton's for ``reference ~ rho * other(T + delay)`` in
    standardised units, scaled by the residuals and inflated for their lag-1 correlation (module docstring)."""
    times = (np.arange(len(reference.values)) + 0.5) * reference.interval
    step = 0.25 * other.interval
    a = reference.values
    b, before, after = (other.at(times + delay_s + s) for s in (0.0, -step, step))
    both = np.isfinite(a).all(1) & np.isfinite(b).all(1) & np.isfinite(before).all(1) & np.isfinite(after).all(1)
    if both.sum() < MIN_OVERLAP:
        return math.inf
    mean_a, sd_a = a[both].mean(0), a[both].std(0)
    mean_b, sd_b = b[both].mean(0), b[both].std(0)
    za, zb = (a[both] - mean_a) / sd_a, (b[both] - mean_b) / sd_b
    slope = (after[both] - before[both]) / (2 * step) / sd_b
    rho = float(np.mean((za * zb).mean(0)))
    residual = za - rho * zb
    sigma2 = float((residual ** 2).sum() / max(residual.size - 2, 1))
    information = rho ** 2 * float((slope ** 2).sum())
    if information <= 0:
        return math.inf
    flat = residual - residual.mean(0)
    r1 = float(np.sum(flat[1:] * flat[:-1]) / max(np.sum(flat * flat), 1e-12))
    r1 = min(max(r1, 0.0), 0.9)
    return math.sqrt(sigma2 / information * (1 + r1) / (1 - r1))


def _second_peak(scores: np.ndarray, best: int) -> float:
    """The best correlation outside the lobe of the peak at ``best`` (where the scores stay above half of it)."""
    finite = np.where(np.isfinite(scores), scores, -np.inf)
    half = 0.5 * finite[best]
    low, high = best, best
    while low - 1 >= 0 and finite[low - 1] > half:
        low -= 1
    while high + 1 < len(finite) and finite[high + 1] > half:
        high += 1
    low, high = min(low, best - 2), max(high, best + 2)
    outside = np.concatenate([finite[:max(low, 0)], finite[high + 1:]])
    return float(outside.max()) if outside.size and np.isfinite(outside.max()) else math.nan


def _refined(reference: MotionSignal, other: MotionSignal, centre: float) -> float:
    """The delay within a frame of ``centre`` (s) that maximises the correlation (module docstring); ``centre``
    where too few samples are covered across that bracket."""
    # The refinement correlates one set of samples throughout (those the other signal covers across the whole
    # bracket): samples entering and leaving the overlap as the delay moves would make steps that pull the peak.
    times = (np.arange(len(reference.values)) + 0.5) * reference.interval
    within = np.ones(len(times), bool)
    for shift in np.linspace(-1.0, 1.0, 9):
        within &= np.isfinite(other.at(times + centre + shift * other.interval)).all(1)
    if within.sum() < MIN_OVERLAP:
        return float(centre)
    found = minimize_scalar(lambda d: -np.nan_to_num(correlation(reference, other, d, within)[0], nan=-2.0),
                            bounds=(centre - other.interval, centre + other.interval), method="bounded",
                            options={"xatol": 1e-4 * other.interval})
    return float(found.x)


def delay_of(reference: MotionSignal, other: MotionSignal, name: str, first: str,
             max_delay_s: float | None = None) -> SourceDelay:
    """``other``'s delay to ``reference`` (module docstring), refused with the reason (`SyncError`)."""
    longest = len(other.values) * other.interval + len(reference.values) * reference.interval
    reach = longest if max_delay_s is None else max_delay_s
    lags = np.arange(-math.ceil(reach / other.interval), math.ceil(reach / other.interval) + 1)
    results = [correlation(reference, other, lag * other.interval) for lag in lags]
    scores = np.array([r for r, _ in results])
    if not np.isfinite(scores).any():
        most = max(n for _, n in results)
        raise SyncError(f"{name} and {first} see the board move at the same time in at most {most} frame pairs at any "
                        f"offset (at least {MIN_OVERLAP}, and half of either's, needed to line them up): record a longer stretch of the "
                        f"board moving where both cameras see it, or give --sync-offsets or --timestamps")
    best = int(np.nanargmax(scores))
    peak = float(scores[best])
    second = _second_peak(scores, best)
    if peak < MIN_PEAK:
        raise SyncError(f"the board's motion as {name} sees it matches {first}'s at no offset (best correlation "
                        f"{peak:.2f} at {lags[best]:+d} frames, {MIN_PEAK:g} needed): check that both see the same "
                        f"board, or give --sync-offsets or --timestamps")
    if np.isfinite(second) and second > MAX_SECOND_PEAK * peak:
        runner = int(np.nanargmax(np.where(np.abs(lags - lags[best]) > 2, scores, -np.inf)))
        raise SyncError(f"{name}'s offset to {first} is ambiguous: the board's motion matches almost as well at "
                        f"{lags[runner]:+d} frames ({second:.2f}) as at {lags[best]:+d} ({peak:.2f}): move the board "
                        f"irregularly (turn it fast, then slow, then still) while every camera sees it, or give "
                        f"--sync-offsets or --timestamps")
    delay = lags[best] * other.interval
    smooth = (reference.smoothed(SMOOTHING), other.smoothed(SMOOTHING))  # (`MotionSignal.smoothed`)
    for _ in range(3):  # a delay refined onto its bracket's end is refined again about the whole frame nearest it
        centre = round(delay / other.interval) * other.interval
        delay = _refined(*smooth, centre)
        if abs(abs(delay - centre) - other.interval) > 1e-3 * other.interval:
            break
    refined, overlap = correlation(reference, other, delay)
    return SourceDelay(delay, delay_std(*smooth, delay), other.interval, max(refined, peak), second, overlap, lags,
                       scores)


def check_motion(signal: MotionSignal, name: str) -> None:
    """`SyncError` for a source whose board barely turns or is seen in too few consecutive frames."""
    if signal.poses and signal.turn_deg < MIN_TURN_DEG:
        raise SyncError(f"the board barely turns in {name} (at most {signal.turn_deg:.1f} degrees from its first "
                        f"pose; {MIN_TURN_DEG:g} needed): a board held still cannot line the videos up in time: turn "
                        f"and move it while every camera sees it, or give --sync-offsets or --timestamps")
    if signal.pairs < MIN_OVERLAP:
        raise SyncError(f"{name} sees the board in two consecutive frames only {signal.pairs} times (at least "
                        f"{MIN_OVERLAP} needed to follow its motion): record the board moving through its view for "
                        f"longer, or give --sync-offsets or --timestamps")


def align(detections: list[list[FrameDetection]], board: BoardSpec, cameras: list[Camera], intervals: list[float],
          names: list[str], *, min_corners: int = 6, board_index: int = 0) -> Alignment:
    """Each source's delay to the first from ``detections[c]`` (every frame of source c, its index the frame
    number; one board), ``cameras[c]`` its intrinsics and ``intervals[c]`` its frame interval (s)."""
    centre = np.array([board.size_m[0] / 2, board.size_m[1] / 2, 0.0])
    signals = []
    for frames, camera, interval, name in zip(detections, cameras, intervals, names):
        poses = board_poses(frames, board, camera, min_corners)
        count = max((f.index for f in frames), default=-1) + 1
        signal = motion_signal(poses, count, interval, centre)
        check_motion(signal, name)
        signals.append(signal)
    delays = [SourceDelay(0.0, 0.0, intervals[0], 1.0, math.nan, signals[0].pairs)]
    delays += [delay_of(signals[0], signal, name, names[0]) for signal, name in zip(signals[1:], names[1:])]
    return Alignment(list(names), delays, signals, board_index)
