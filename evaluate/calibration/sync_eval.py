"""``python -m evaluate.calibration.sync_eval``: automatic time alignment (`deepcharuco.calibration.time_sync`) measured.

- drawn rigs with exact sub-frame delays: a board waved smoothly (`waved_board`) through `rig_views.rig_cameras`'
  rigs, each camera's corners projected exactly (plus 0.1 px noise) at its own frame times ``(k + delay) / fps``;
  per seed and camera the estimated delay's error (frames) and its stated deviation;
- with ``--realdata DIR``: caliscope's four synchronised webcams (``DIR/caliscope_calibration``, 6 fps) detected
  once per detector (cached in ``--cache``), then cut at known offsets (frames dropped from the start of some
  sources) and resampled to 3 fps (every other frame): the whole-frame delay found against the cut, the
  sub-frame delay against the uncut videos' own, and the rig solved from the auto-aligned frames (caliscope's
  intrinsics held, as ``--camera``) against the rig from the same frames aligned by hand (the cuts as
  ``--sync-offsets``): rotation (degrees) and centre (mm per metre of baseline) differences.
"""

from __future__ import annotations

import argparse
import json
import math
import pickle
import sys
from pathlib import Path

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.calibration.rig_model import rotation_angle_deg
from deepcharuco.calibration.time_sync import align
from deepcharuco.calibration.views import (
    FrameDetection,
    SelectionOptions,
    border_margin,
)
from deepcharuco.cli.calibrate_rig import instants_by_time, solve_rig
from deepcharuco.cli.rig_sync import aligned_times, renumbered
from deepcharuco.geometry.camera import Camera, read_camera
from evaluate.calibration.rig_views import RIG_BOARD, rig_cameras

CUTS = ([0, 3, 7, 1], [5, 0, 2, 9], [0, 12, 0, 4], [10, 0, 0, 0])  # frames dropped from each caliscope video's start


def waved_board(rng: np.random.Generator, target: np.ndarray, times: np.ndarray, board: BoardSpec = RIG_BOARD
                ) -> tuple[np.ndarray, np.ndarray]:
    """Board poses (R (N, 3, 3), t (N, 3), board -> camera 0's frame) at ``times`` (s) of a board waved about
    ``target``: each rotation angle and coordinate a sum of three sinusoids of 0.15-0.8 Hz (up to 35 degrees,
    0.3 m), as a hand moves it; the same ``rng`` state gives the same motion at any times."""
    frequencies = rng.uniform(0.15, 0.8, (6, 3))
    phases = rng.uniform(0, 2 * math.pi, (6, 3))
    amplitudes = np.concatenate([np.radians(rng.uniform(5, 14, (3, 3))), rng.uniform(0.04, 0.12, (3, 3))])
    wave = (amplitudes[None] * np.sin(2 * math.pi * frequencies[None] * times[:, None, None] + phases[None])).sum(2)
    centre = np.array([board.size_m[0] / 2, board.size_m[1] / 2, 0.0])
    rotations = np.stack([cv2.Rodrigues(w[:3])[0] for w in wave])
    translations = target + wave[:, 3:] - rotations @ centre
    return rotations, translations


def drawn_detections(seed: int, delays: list[float], fps: list[float], seconds: float = 8.0, noise: float = 0.1,
                     size: tuple[int, int] = (640, 480), noise_seed: int = 0
                     ) -> tuple[list[list[FrameDetection]], list[Camera]]:
    """Each camera's exact corners (plus ``noise`` px) in every frame of a ``seconds`` recording at ``fps[c]``,
    camera c's frame k taken at ``(k + delays[c]) / fps[c]`` s of the board's motion (its delay: ``delays[c]``
    frames of it), and the cameras."""
    rng = np.random.default_rng(seed)
    cameras, rotations, translations, target = rig_cameras(rng, len(delays), size)
    motion = rng.bit_generator.state
    points = RIG_BOARD.object_points()
    noisy = np.random.default_rng([seed, 7, noise_seed])
    detections = []
    for camera, R, t, delay, rate in zip(cameras, rotations, translations, delays, fps):
        rng.bit_generator.state = motion
        times = (np.arange(int(seconds * rate)) + delay) / rate
        board_r, board_t = waved_board(rng, target, times)
        frames = []
        for k, (R_b, t_b) in enumerate(zip(board_r, board_t)):
            R_c, t_c = R @ R_b, R @ t_b + t
            pixels = camera.project(points, cv2.Rodrigues(R_c)[0], t_c)
            inside = ((pixels > 15) & (pixels < np.array(size) - 15)).all(1) & ((points @ R_c.T + t_c)[:, 2] > 0)
            ids = np.flatnonzero(inside) if inside.sum() >= 6 else np.zeros(0, np.int64)
            frames.append(FrameDetection(k, str(k), ids, pixels[ids] + noisy.normal(0, noise, (len(ids), 2))))
        detections.append(frames)
    return detections, cameras


def drawn_experiment(seeds: list[int]) -> list[dict]:
    """Per seed: 3 cameras at 30 fps with sub-frame delays, and one camera at 25 fps."""
    rows = []
    for seed in seeds:
        rng = np.random.default_rng([seed, 3])
        delays = [0.0, *rng.uniform(-6, 6, 2)]
        for fps in ([30.0, 30.0, 30.0], [30.0, 25.0, 30.0]):
            detections, cameras = drawn_detections(seed, delays, fps)
            found = align(detections, RIG_BOARD, cameras, [1 / r for r in fps], ["cam0", "cam1", "cam2"])
            for c in (1, 2):
                # camera c's frame k shows the motion at (k + delay_c) / fps_c: what camera 0 shows at time T,
                # camera c shows at T - delay_c / fps_c on its clock (delay_s = -delay_c / fps_c).
                true = -delays[c]
                rows.append({"seed": seed, "fps": fps[c], "camera": c, "true_frames": true,
                             "found_frames": found.delays[c].frames, "error_frames": found.delays[c].frames - true,
                             "std_frames": found.delays[c].std_frames, "peak": found.delays[c].peak})
    return rows


def cached_detections(session: Path, detector: str, cache: Path) -> list[list[FrameDetection]]:
    """Every frame of caliscope's four videos detected by ``detector`` (read from ``cache`` where there)."""
    path = cache / f"caliscope_{detector}.pkl"
    if path.is_file():
        return pickle.loads(path.read_bytes())
    from evaluate.calibration.rig_eval import detect_all, make_detector
    from evaluate.speed.realistic import video_frames

    board = BoardSpec.load(session / "board.yaml")
    frames = [video_frames(v) for v in sorted(session.glob("cam_*.mp4"))]
    detections = detect_all(frames, make_detector(detector, board)[0], False, detector)
    cache.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps(detections))
    return detections


def cut(frames: list[FrameDetection], start: int, every: int = 1) -> list[FrameDetection]:
    """The frames of a video with its first ``start`` frames dropped, then every ``every``-th kept, renumbered."""
    return [FrameDetection((f.index - start) // every, f.name, f.ids, f.corners, f.sharpness, f.covariances)
            for f in frames if f.index >= start and (f.index - start) % every == 0]


def real_experiment(folder: Path, detector: str, cache: Path) -> dict:
    session = folder / "caliscope_calibration"
    board = BoardSpec.load(session / "board.yaml")
    names = [f"cam_{c}" for c in range(4)]
    cameras = [read_camera(session / f"camera_{name}.yaml") for name in names]
    given = [str(session / f"camera_{name}.yaml") for name in names]
    detections = cached_detections(session, detector, cache)
    uncut = align(detections, board, cameras, [1 / 6] * 4, names)
    options = SelectionOptions(border_px=border_margin("refinenet" if detector != "opencv" else "subpix"))
    sizes = [(1280, 720)] * 4
    rows = {"uncut_delays_frames": [d.frames for d in uncut.delays], "uncut_std_frames": [d.std_frames for d in uncut.delays],
            "cuts": []}
    for cuts in CUTS:
        frames = [cut(f, n) for f, n in zip(detections, cuts)]
        found = align(frames, board, cameras, [1 / 6] * 4, names)
        true = [cuts[c] - cuts[0] for c in range(4)]  # frames to skip at c's start relative to the first
        whole = [int(d.lags[int(np.nanargmax(d.scores))]) if len(d.lags) else 0 for d in found.delays]
        row = {"cuts": cuts, "true_whole_frames": [-t for t in true], "correlation_peak_frames": whole,
               "found_frames": [d.frames for d in found.delays],
               "found_minus_cut_minus_uncut": [d.frames + t - u.frames for d, t, u in zip(found.delays, true, uncut.delays)]}
        # The rig from the frames aligned automatically (nearest instants) and by hand (the cuts undone).
        times = aligned_times([[f] for f in frames], found)
        auto = renumbered([[f] for f in frames], instants_by_time(times))
        low = min(true)
        hand = [[[FrameDetection(f.index + t - low, f.name, f.ids, f.corners, f.sharpness, f.covariances)
                  for f in fr]] for fr, t in zip(frames, true)]
        rigs = [solve_rig(d, sizes, names, [board], options, given=given) for d in (auto, hand)]
        baseline = max(np.linalg.norm(rigs[1].centre(a) - rigs[1].centre(b)) for a in range(4) for b in range(4))
        row["rig_rotation_deg"] = [rotation_angle_deg(rigs[0].rotations[c] @ rigs[1].rotations[c].T) for c in range(4)]
        row["rig_centre_mm_per_m"] = [1000 * float(np.linalg.norm(rigs[0].centre(c) - rigs[1].centre(c))) / baseline
                                      for c in range(4)]
        # The same pairs as by hand (the hand instants count from the earliest start: camera 0's frame k is
        # instant k - low there, k here).
        row["paired_like_hand"] = [sorted(f.index for f in a[0]) == sorted(f.index + low for f in h[0])
                                   for a, h in zip(auto, hand)]
        rows["cuts"].append(row)
    frames = [cut(f, 0, 2 if c in (1, 3) else 1) for c, f in enumerate(detections)]
    half = align(frames, board, cameras, [1 / 6, 1 / 3, 1 / 6, 1 / 3], names)
    rows["half_rate_cam1_cam3_ms"] = [1000 * d.delay_s for d in half.delays]
    rows["half_rate_std_ms"] = [1000 * d.std_s for d in half.delays]
    rows["uncut_ms"] = [1000 * d.delay_s for d in uncut.delays]
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m evaluate.calibration.sync_eval", description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="*", default=[1, 2, 3, 4, 5])
    parser.add_argument("--realdata", type=Path, default=None, help="folder holding caliscope_calibration/")
    parser.add_argument("--detectors", nargs="+", choices=["opencv", "deep"], default=["opencv", "deep"])
    parser.add_argument("--cache", type=Path, default=Path("report/sync_cache"), help="detections kept here")
    parser.add_argument("--out", type=Path, default=Path("report/sync_eval.json"))
    args = parser.parse_args(argv)
    results = {"drawn": drawn_experiment(args.seeds)}
    for row in results["drawn"]:
        print(json.dumps(row), flush=True)
    if args.realdata is not None:
        for detector in args.detectors:
            results[f"caliscope_{detector}"] = real_experiment(args.realdata, detector, args.cache)
            print(json.dumps(results[f"caliscope_{detector}"], indent=1), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1))
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
