"""Rendered calibration videos with a known distorted camera: ``python -m evaluate.calibration.calibration_sequences``.

Truth for `deepcharuco.cli.calibrate`: a board waved by hand in front of a still camera whose lens
distortion is known. One camera per k1 in `K1_VALUES` (k2 = k1^2, which keeps the lens one to one,
small tangential terms, square pixels, a principal point a few pixels off centre, 55-70 degrees
of horizontal field of view), and three videos of it, one shard each (shard index = number):

- ``k1<k1>-good`` (e.g. ``k1-0.40-good``): 400 lux, the board held still at each view;
- ``k1<k1>-1lux``: the same views (the same renders) at 1 lux: the sensor's gain and noise;
- ``k1<k1>-shake``: the board moving along its path and the hand shaking (the shake of
  `evaluate.paper.sequences`' motion videos), each frame rendered with real motion blur over its
  exposure, at 60-200 lux; labelled at the shutter centre.

``--conditions`` renders some of them (good light and 1 lux share their renders; shake needs its own):
the still frames are the same with or without the shake video.

The waving (`hand_waved_pose`): the board's centre follows a 3:2 Lissajous figure over the whole
image (so parts of it leave the frame at the edges and corners, where distortion is strongest),
its tilt towards the camera sweeps +-40 degrees about both axes, it rolls and comes nearer and
farther; one sweep lasts `SWEEP_S` seconds and ``--frames`` frames sample it.

Distortion (`datagen.lens`): each frame is rendered by Cycles through a wider pinhole camera and
resampled into the distorted image, so a corner lies exactly where ``cv2.projectPoints`` with the
distorted camera puts it; the render's radiance is distorted before the sensor adds its noise.
Shards follow docs/conventions.md's schema; K is the pinhole matrix and ``meta/dist_k1 .. dist_k3`` hold the
distortion (OpenCV's k1 k2 p1 p2 k3). The room is the scene sampler's (`datagen.scene`), without
floor and clutter: the camera moves around the board here, which for calibration is the same as the
board moving in front of the camera (only their relative pose counts).

Frame k of camera c is a pure function of (seed, c, k, arguments): scenes from
``default_rng([seed, 100 + c, attempt])``, sensor noise from ``default_rng([seed, 100 + c, attempt, 1, k, condition])``.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import ClassVar

import cv2
import numpy as np

from datagen.lens import monotonic_k2, pixels_to_rays
import deepcharuco
from deepcharuco.boards.board import BoardSpec
from deepcharuco.cli.common import output_folder
from deepcharuco.core.errors import DeepCharucoError
from evaluate.paper.sequences import SceneJob

K1_VALUES = (-0.4, -0.15, 0.1)
CONDITIONS = ("good", "1lux", "shake")
GOOD_LUX = 400.0
DARK_LUX = 1.0
SWEEP_S = 30.0  # one pass of the waving path; frames sample it
TILT_DEG = 40.0
REACH = (0.32, 0.30)  # the board centre's sweep either side of the image centre, in image widths / heights
SEED_OFFSET = 100  # camera c draws from default_rng([seed, 100 + c, ...]): never evaluate.paper.sequences' streams


@dataclass(frozen=True)
class CalibrationSequence:
    """One video: ``number`` (its shard index), ``name``, the camera's index ``camera`` and ``k1``,
    and ``condition`` ("good" | "1lux" | "shake")."""

    number: int
    name: str
    camera: int
    k1: float
    condition: str


def _all() -> tuple[CalibrationSequence, ...]:
    return tuple(CalibrationSequence(3 * c + j, f"k1{k1:+.2f}-{condition}", c, k1, condition)
                 for c, k1 in enumerate(K1_VALUES) for j, condition in enumerate(CONDITIONS))


CALIBRATION_SEQUENCES = _all()
NAMES = tuple(s.name for s in CALIBRATION_SEQUENCES)


def true_camera(rng: np.random.Generator, k1: float, image_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(K (3, 3), dist (5,)) of a sequence camera: square pixels (the renderer's), 55-70 degrees of
    horizontal field, principal point within 6 px of the centre, k2 = `monotonic_k2` (k1), tangential
    terms below 1e-3, k3 = 0."""
    width, height = image_size
    focal = (width / 2.0) / math.tan(math.radians(rng.uniform(55.0, 70.0)) / 2.0)
    cx, cy = (width - 1) / 2.0 + rng.uniform(-6, 6), (height - 1) / 2.0 + rng.uniform(-6, 6)
    K = np.array([[focal, 0.0, cx], [0.0, focal, cy], [0.0, 0.0, 1.0]])
    dist = np.array([k1, monotonic_k2(k1), *rng.uniform(-1e-3, 1e-3, size=2), 0.0])
    return K, dist


@dataclass(frozen=True)
class WavingPath:
    """The random constants of one hand's waving (phases, jitter); `hand_waved_pose` evaluates it."""

    phases: tuple[float, ...]
    roll_deg: float
    size: tuple[float, float]  # board diagonal / image width: mean, amplitude

    @classmethod
    def draw(cls, rng: np.random.Generator) -> "WavingPath":
        return cls(phases=tuple(float(p) for p in rng.uniform(0.0, 2 * math.pi, size=6)),
                   roll_deg=float(rng.uniform(-30.0, 30.0)), size=(float(rng.uniform(0.6, 0.75)), 0.2))


def _rotation_towards(direction: np.ndarray) -> np.ndarray:
    """(3, 3) the smallest rotation taking the optical axis (0, 0, 1) to the unit ``direction``."""
    axis = np.cross([0.0, 0.0, 1.0], direction)
    sine = float(np.linalg.norm(axis))
    if sine < 1e-12:
        return np.eye(3)
    return cv2.Rodrigues(axis / sine * math.atan2(sine, float(direction[2])))[0]


def hand_waved_pose(path: WavingPath, t: float, board: BoardSpec, K: np.ndarray, dist: np.ndarray,
                    image_size: tuple[int, int]) -> np.ndarray:
    """(4, 4) board -> camera transform at time ``t`` (s) of the waving: the board's centre on a 3:2
    Lissajous figure over the image (its distorted pixel, 0.32 W and 0.30 H from the centre at most: the board reaches the edges),
    tilted towards the line of sight by up to `TILT_DEG` about two axes, rolled, at the distance that
    makes its diagonal ``size`` image widths (pinhole)."""
    width, height = image_size
    phase = 2 * math.pi * t / SWEEP_S
    p = path.phases
    target = np.array([(width - 1) / 2 + REACH[0] * width * math.sin(3 * phase + p[0]),
                       (height - 1) / 2 + REACH[1] * height * math.sin(2 * phase + p[1])])
    ray = np.append(pixels_to_rays(target[None], K, dist)[0], 1.0)
    ray /= np.linalg.norm(ray)
    tilt_x = TILT_DEG * math.sin(5 * phase + p[2])
    tilt_y = TILT_DEG * math.sin(7 * phase + p[3])
    roll = path.roll_deg + 25.0 * math.sin(phase + p[4])
    size = path.size[0] + path.size[1] * math.sin(4 * phase + p[5])
    diagonal = math.hypot(*board.size_m)
    distance = K[0, 0] * diagonal / (size * width)
    rx = cv2.Rodrigues(np.array([math.radians(tilt_x), 0.0, 0.0]))[0]
    ry = cv2.Rodrigues(np.array([0.0, math.radians(tilt_y), 0.0]))[0]
    rz = cv2.Rodrigues(np.array([0.0, 0.0, math.radians(roll)]))[0]
    rotation = _rotation_towards(ray) @ rx @ ry @ rz
    centre = np.array([board.size_m[0] / 2, board.size_m[1] / 2, 0.0])
    transform = np.eye(4)
    transform[:3, :3] = rotation
    transform[:3, 3] = distance * ray - rotation @ centre
    return transform


def frame_times(count: int, rng: np.random.Generator) -> np.ndarray:
    """(count,) times (s) of the frames over one sweep: evenly spread, each jittered by a third of the spacing."""
    spacing = SWEEP_S / count
    return (np.arange(count) + 0.5 + rng.uniform(-1 / 3, 1 / 3, size=count)) * spacing


def pose_of(transform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rvec (3,), tvec (3,)) of a (4, 4) board -> camera transform."""
    return cv2.Rodrigues(transform[:3, :3])[0].ravel(), transform[:3, 3].copy()


# ----------------------------------------------------------------------------------------- rendering
def calibration_config(width: int, height: int, samples: int) -> "SceneConfig":
    """The scene sampler for the room, lights and board look: the board alone (no clutter, occluders,
    distractors or shadow casters), matte or glossy paper, at `GOOD_LUX`."""
    from datagen.scene import SceneConfig

    return SceneConfig(width=width, height=height, lux=(GOOD_LUX, GOOD_LUX), max_view_angle_deg=35.0,
                       out_of_frame_p=0.0, negative_p=0.0, distractor_p=0.0, shake_p=0.0, lamp_count=(0, 2),
                       spot_p=0.0, shadow_p=0.0, occluder_p=0.0, clutter_count=(0, 0), board_kinds_p=(0.75, 0.25, 0.0),
                       samples=samples)


@dataclass(frozen=True)
class CalibrationJob(SceneJob):
    """A run of the calibration sequences (picklable for the worker processes)."""

    command: ClassVar[str] = "evaluate.calibration.calibration_sequences"
    conditions: tuple[str, ...] = CONDITIONS

    def content(self) -> dict:
        # Named only when not all three: shards of a full run (before the option existed) still resume.
        extra = {} if tuple(self.conditions) == CONDITIONS else {"conditions": list(self.conditions)}
        return {**super().content(), **extra}

    def numbers(self, cameras: list[int]) -> list[int]:
        """The shard numbers this job writes for ``cameras``."""
        return [s.number for s in CALIBRATION_SEQUENCES if s.camera in cameras and s.condition in self.conditions]


def _noise_rng(seed: int, camera: int, attempt: int, frame: int, condition: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), SEED_OFFSET + int(camera), int(attempt), 1, int(frame), int(condition)])


def _camera_world(board_matrix: np.ndarray, board_to_camera: np.ndarray) -> np.ndarray:
    """(4, 4) world from OpenCV camera, for a board placed at ``board_matrix`` seen at ``board_to_camera``."""
    return board_matrix @ np.linalg.inv(board_to_camera)


def _shaken(shake, t: float) -> np.ndarray:
    """(4, 4) camera-at-rest from shaken-camera transform at time t (`evaluate.paper.sequences._shake`)."""
    rotation_vector, offset = shake(t)
    transform = np.eye(4)
    transform[:3, :3] = cv2.Rodrigues(np.asarray(rotation_vector, np.float64))[0]
    transform[:3, 3] = offset
    return transform


def distorted_labels(board: BoardSpec, transform: np.ndarray, K: np.ndarray, dist: np.ndarray,
                     image_size: tuple[int, int], unoccluded: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(corners (C, 2) float32, visible (C,) bool) of the board at ``transform`` (board -> camera) through
    the distorted camera: ``cv2.projectPoints``; NaN behind the camera; visible = in the image, in front,
    and ``unoccluded`` (the renderer's ray casts)."""
    rvec, tvec = pose_of(transform)
    points = board.object_points()
    corners, _ = cv2.projectPoints(points, rvec, tvec, K, dist)
    corners = corners.reshape(-1, 2).astype(np.float32)
    in_front = (points @ transform[:3, :3].T + transform[:3, 3])[:, 2] > 0.05
    corners[~in_front] = np.nan
    width, height = image_size
    inside = (in_front & (corners[:, 0] >= -0.5) & (corners[:, 0] < width - 0.5)
              & (corners[:, 1] >= -0.5) & (corners[:, 1] < height - 0.5))
    return corners, inside & np.asarray(unoccluded, bool)


def render_camera(job: CalibrationJob, camera: int) -> int:
    """Render camera ``camera``'s three sequences (good, 1 lux, shake) as shards 3c, 3c+1, 3c+2."""
    from datagen.frames import expose, luminance_scale, render_labelled, scene_meta
    from datagen.lens import distort_image, distortion_maps, wide_camera
    from datagen.scene import exposure_time_for, sample_scene
    from datagen.sensor import SensorParams
    from datagen.shards import FrameLabels, write_shard
    from datagen.workers import report_progress
    from evaluate.paper.sequences import MOTION_LUX, _shake

    sequences = [s for s in CALIBRATION_SEQUENCES if s.camera == camera and s.condition in job.conditions]
    size = (job.width, job.height)
    attempt = 0
    rng = np.random.default_rng([job.seed, SEED_OFFSET + camera, attempt])
    K, dist = true_camera(rng, K1_VALUES[camera], size)
    K_wide, wide_size = wide_camera(K, dist, size)
    maps = distortion_maps(K, dist, size, K_wide)
    scene = sample_scene(rng, job.board.size_m, calibration_config(*wide_size, job.samples))
    # The wall behind the board only: the camera travels where the sampler's floor and clutter could be.
    # Denoised: one render serves a good-light and a 1-lux frame, and Monte Carlo noise at a few samples would
    # otherwise be most of a good-light frame's noise (evaluate.paper.sequences does the same for its lit frames).
    scene = replace(scene, K=K_wide, shapes=[s for s in scene.shapes if s.role == "room"][:1], denoise=True)
    path = WavingPath.draw(rng)
    times = frame_times(job.frames, rng)
    shake = _shake(rng)
    shake_lux = float(math.exp(rng.uniform(*np.log(MOTION_LUX))))
    sensor = SensorParams()
    renders = {"static": [], "shake": []}
    # The static renders come first and draw their seeds first: a run without the shake video renders the
    # same good-light and 1-lux frames as a full one.
    static = any(s.condition != "shake" for s in sequences)
    for k, t in enumerate(times if static else []):
        pose = hand_waved_pose(path, t, job.board, K, dist, size)
        spec = replace(scene, trajectory=np.stack([_camera_world(scene.board_matrix, pose)] * 3),
                       render_seed=int(rng.integers(0, 2**31 - 1)))
        renders["static"].append((pose, spec, render_labelled(spec, job.board, threads=job.threads, device=job.device)))
        report_progress(1)
    exposure_s = exposure_time_for(shake_lux, scene.board_look, sensor)
    for k, t in enumerate(times if any(s.condition == "shake" for s in sequences) else []):
        poses = [np.linalg.inv(_shaken(shake, t + dt)) @ hand_waved_pose(path, t + dt, job.board, K, dist, size)
                 for dt in (-exposure_s / 2, 0.0, exposure_s / 2)]
        spec = replace(scene, trajectory=np.stack([_camera_world(scene.board_matrix, p) for p in poses]),
                       lux=shake_lux, exposure_s=exposure_s, render_seed=int(rng.integers(0, 2**31 - 1)))
        renders["shake"].append((poses[1], spec, render_labelled(spec, job.board, threads=job.threads, device=job.device)))
        report_progress(1)

    for sequence in sequences:
        index = CONDITIONS.index(sequence.condition)  # the noise stream of a condition, whichever others are rendered
        lux = {"good": GOOD_LUX, "1lux": DARK_LUX}.get(sequence.condition, shake_lux)
        frames = []
        for k, (pose, spec, shot) in enumerate(renders["shake" if sequence.condition == "shake" else "static"]):
            spec = replace(spec, lux=lux, exposure_s=exposure_time_for(lux, spec.board_look, sensor)
                           if sequence.condition != "shake" else spec.exposure_s)
            scale = luminance_scale(shot.luminance, spec, shot.white_mask)
            luminance = distort_image((shot.luminance * scale).astype(np.float32), K, dist, size, K_wide, maps=maps)
            image, exposure = expose(luminance.astype(np.float64), spec.exposure_s,
                                     _noise_rng(job.seed, camera, attempt, k, index), sensor)
            corners, visible = distorted_labels(job.board, pose, K, dist, size, shot.visible)
            rvec, tvec = pose_of(pose)
            meta = {"seed": int(job.seed), "frame": k, "sequence": sequence.name, "sequence_number": sequence.number,
                    "sequence_frame": k, "condition": sequence.condition, "calibration_camera": camera,
                    "time_s": float(times[k]),
                    **{f"dist_{name}": float(v) for name, v in zip(("k1", "k2", "p1", "p2", "k3"), dist)},
                    **scene_meta(job.board, spec, visible, sensor, exposure)}
            meta["focal_px"] = float(K[0, 0])
            frames.append(FrameLabels(image=image, corners=corners, visible=visible, K=K.astype(np.float32),
                                      rvec=rvec.astype(np.float32), tvec=tvec.astype(np.float32), meta=meta))
        generator = {"package": "deepcharuco", "version": deepcharuco.__version__,
                     "command": "evaluate.calibration.calibration_sequences", "args": job.content(), "sequence": sequence.name,
                     "device": job.device}
        write_shard(job.out, sequence.number, frames, job.board, generator)
    return len(sequences) * job.frames


def renders_per_camera(job: CalibrationJob) -> int:
    """Cycles renders of one camera: the still views (good light and 1 lux share them) and the shaken ones."""
    return job.frames * (any(c != "shake" for c in job.conditions) + ("shake" in job.conditions))


def read_truth(shard: str | Path) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """(K (3, 3), dist (5,), (width, height)) of a calibration sequence shard's camera."""
    from datagen.shards import ShardReader

    reader = ShardReader(shard)
    try:
        frame = reader[0]
        dist = np.array([frame.meta[f"dist_{name}"] for name in ("k1", "k2", "p1", "p2", "k3")], np.float64)
        height, width = frame.image.shape
        return frame.K.astype(np.float64), dist, (width, height)
    finally:
        reader.close()


def run(job: CalibrationJob, cameras: list[int], *, resume: bool, workers: int = 1, quiet: bool = False) -> dict:
    """Render the selected cameras' sequences missing from ``job.out``; returns index.json's content."""
    from datagen.render import check_existing, remove_stale_temporaries, run_shard_tasks
    from datagen.shards import update_index

    done = check_existing(job, job.numbers(cameras), resume)
    todo = [c for c in cameras if not set(job.numbers([c])) <= done]
    out = output_folder(job.out)  # a writable folder, before anything is rendered
    remove_stale_temporaries(out, job.numbers(todo))
    renders = renders_per_camera(job)
    if not quiet:
        print(f"evaluate.calibration.calibration_sequences: {len(todo)} camera(s) x {len(job.conditions)} sequence(s) "
              f"({', '.join(job.conditions)}) of {job.frames} frames ({renders} renders each) into {out}", file=sys.stderr)
    if todo:
        run_shard_tasks(render_camera, [(job, c) for c in todo], [job.numbers([c])[0] for c in todo], out, noun="camera",
                        total=renders * len(todo), unit="render", workers=workers, tasks_per_child=1, quiet=quiet)
    return update_index(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m evaluate.calibration.calibration_sequences", formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description="Render calibration videos of a hand-waved board through known distorted cameras (k1 "
                    f"{', '.join(f'{k:+.2f}' for k in K1_VALUES)}): good light, 1 lux, shake; one shard each.",
        epilog=f"Sequences (shard index = position): {', '.join(NAMES)}.")
    parser.add_argument("--out", default="data/calibration", help="output folder of shard-*.h5 + index.json")
    parser.add_argument("--frames", type=int, default=40, help="frames per sequence (views of one sweep)")
    parser.add_argument("--seed", type=int, default=0, help="run seed")
    parser.add_argument("--samples", type=int, default=4, help="Cycles samples per pixel (denoised)")
    parser.add_argument("--cameras", type=int, nargs="+", default=None,
                        help=f"render only these cameras (0..{len(K1_VALUES) - 1}: k1 = {K1_VALUES})")
    parser.add_argument("--conditions", nargs="+", choices=CONDITIONS, default=list(CONDITIONS),
                        help="render only these videos of each camera (good and 1lux share their renders; shake "
                             "doubles the work)")
    parser.add_argument("--resume", action="store_true", help="continue a run in --out")
    parser.add_argument("--width", type=int, default=320, help="image width in pixels")
    parser.add_argument("--height", type=int, default=240, help="image height in pixels")
    parser.add_argument("--board", default=None, help="BoardSpec file (default: the paper's 5x5 DICT_5X5_50 board)")
    parser.add_argument("--workers", type=int, default=1, help="parallel render processes (one camera each)")
    parser.add_argument("--threads", type=int, default=0, help="Cycles threads per worker (0: cores / workers)")
    parser.add_argument("--device", choices=("cpu", "gpu"), default="cpu", help="Cycles device")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    problems = [f"--{name} must be >= {low}, got {getattr(args, name)}"
                for name, low in (("frames", 2), ("samples", 1), ("width", 64), ("height", 48), ("workers", 1),
                                  ("threads", 0), ("seed", 0)) if getattr(args, name) < low]
    cameras = args.cameras if args.cameras is not None else list(range(len(K1_VALUES)))
    problems += [f"--cameras takes 0..{len(K1_VALUES) - 1}, got {c}" for c in cameras if not 0 <= c < len(K1_VALUES)]
    if problems:
        parser.error("; ".join(problems))
    try:
        board = BoardSpec.load(args.board) if args.board else BoardSpec()
        threads = args.threads or max(1, (os.cpu_count() or 1) // args.workers)
        job = CalibrationJob(out=args.out, seed=args.seed, frames=args.frames, board=board, width=args.width,
                             height=args.height, samples=args.samples, device=args.device, threads=threads,
                             conditions=tuple(c for c in CONDITIONS if c in args.conditions))
        started = time.perf_counter()
        index = run(job, sorted(set(cameras)), resume=args.resume, workers=args.workers, quiet=args.quiet)
    except DeepCharucoError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    if not args.quiet:
        print(f"evaluate.calibration.calibration_sequences: {index['frames']} frame(s) in {len(index['shards'])} sequence(s) in "
              f"{args.out} ({time.perf_counter() - started:.0f} s)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
