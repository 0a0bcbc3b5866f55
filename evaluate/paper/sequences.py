"""Rendered twins of the paper's 26 evaluation videos: ``python -m evaluate.paper.sequences``.

The paper filmed a static board with a still webcam: 20 videos at 10 light levels (two each),
3 with a moving shadow, 3 with camera shake. Here each video is a sequence of ``--frames``
rendered frames (one shard each, shard index = the sequence's number):

- ``lux-700-a`` .. ``lux-0.3-b`` (0-19): the board under one illuminance. The geometry never
  changes, so the scene is rendered ONCE; every frame scales that radiance to its own lux (as
  `datagen.frames.luminance_scale` does) and goes through the sensor with fresh noise and its
  own auto-exposure, as a webcam adapting to the light;
- ``shadow-1..3`` (20-22): one spotlight; a caster (a rod, a ball or a box) between it and
  the board sweeps its shadow across the board, one render per frame. The caster never comes
  between the camera and the board (checked on the geometry before rendering);
- ``motion-1..3`` (23-25): hand-held shake about a fixed rest pose (sums of sinusoids in
  rotation and translation, 30 fps), each frame a Cycles render with real motion blur over
  its exposure; labels are the pose at the shutter centre, ``blur_px`` the corners' longest
  path over the shutter.

Every sequence starts with 30 well-lit, static frames (the paper's auto-labelling recipe
averages them): lux sequences at max(level, 400 lux), shadow and motion sequences at their
own light without the shadow or the shake; those 30 frames share one render at
4 x ``--samples``, denoised (OpenImageDenoise): its Monte Carlo noise would be in every one of them.

Scenes come from `datagen.scene.sample_scene` with `evaluation_config` (no negatives,
distractor boards or occluders, moderate view angles, flat-shaded clutter), drawn from
``default_rng([seed, number, attempt])``; a scene is redrawn (attempt + 1) until the whole
board is in view and all its corners unoccluded, shake included. Frame k's sensor noise comes
from ``default_rng([seed, number, attempt, 1, k])``. Same seed and arguments, same pixels;
with ``SOURCE_DATE_EPOCH`` set, the same bytes.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from dataclasses import dataclass, replace
from typing import Callable, ClassVar

import cv2
import numpy as np

from blender_scenes.conversions import board_pose_in_camera, rigid
from datagen.frames import LabelledRender, expose, luminance_scale, render_labelled, scene_meta
from datagen.render import check_existing, remove_stale_temporaries, run_shard_tasks
from datagen.scene import (
    Light, SceneConfig, SceneSpec, Shape, aim_lamp, exposure_time_for, sample_scene, sample_surface, unit_vector,
)
from datagen.sensor import SensorParams
from datagen.shards import FrameLabels, update_index, write_shard
from datagen.workers import report_progress
import deepcharuco
from deepcharuco.boards.board import BoardSpec
from deepcharuco.cli.common import output_folder, run_command
from deepcharuco.core.errors import DeepCharucoError

LUX_LEVELS = (700.0, 400.0, 100.0, 50.0, 30.0, 10.0, 5.0, 3.0, 1.0, 0.3)  # the paper's table
LIT_FRAMES = 30  # the paper's recipe averages the first 30 frames
LIT_LUX = 400.0
FPS = 30.0
# One render serves 30+ frames, so its Monte Carlo noise would be frozen into all of them: it gets 4x the
# samples and OpenImageDenoise (measured: autolabel error vs truth 0.07-0.10 px median, as at 64 spp).
STATIC_SAMPLES_FACTOR = 4
SHADOW_LUX = (250.0, 700.0)  # a lamp-lit desk
MOTION_LUX = (60.0, 200.0)  # indoor light: exposures of 13-33 ms, long enough for shake to blur
MOTION_PEAK_RAD_S = (2.5, 6.0)  # hand-held shake: peak angular speed
VIEW_MARGIN_PX = 4.0  # the board's outline stays this far inside the image
MAX_ATTEMPTS = 50
MAX_DRAWS = 20  # shadow / shake draws per scene before the scene is redrawn
# Flat-shaded primitives only: Blender 5.0 computes the vertex normals of smooth-shaded meshes
# (sphere, cylinder, cone) with run-to-run differences in the last bit, which the sensor's Poisson
# sampling turns into different frames (measured); a sequence must be the same bytes every time.
FLAT_SHAPES = ("cube", "icosphere")


@dataclass(frozen=True)
class Sequence:
    """One video of the set: ``number`` (its shard index), ``name``, ``kind`` ("lux" | "shadow" |
    "motion") and, for lux sequences, ``level``: the illuminance after the lit frames."""

    number: int
    name: str
    kind: str
    level: float | None = None


def _all_sequences() -> tuple[Sequence, ...]:
    sequences = []
    for level in LUX_LEVELS:
        for scene in "ab":
            sequences.append(Sequence(len(sequences), f"lux-{level:g}-{scene}", "lux", level))
    for kind in ("shadow", "motion"):
        for i in range(1, 4):
            sequences.append(Sequence(len(sequences), f"{kind}-{i}", kind))
    return tuple(sequences)


SEQUENCES = _all_sequences()
SEQUENCE_NAMES = tuple(s.name for s in SEQUENCES)


def evaluation_config(width: int = 320, height: int = 240, samples: int = 4,
                      sensor: SensorParams = SensorParams()) -> SceneConfig:
    """The scene sampler for the evaluation videos: the target board alone and wholly in view, at
    moderate angles, on a webcam; the light level is set per frame afterwards."""
    return SceneConfig(width=width, height=height, hfov_deg=(50.0, 75.0), lux=(LIT_LUX, LIT_LUX),
                       board_diag_frac=(0.7, 1.0), max_view_angle_deg=35.0, out_of_frame_p=0.0, negative_p=0.0,
                       distractor_p=0.0, shake_p=0.0, lamp_count=(0, 2), spot_p=0.15, shadow_p=0.0, occluder_p=0.0,
                       clutter_kinds=FLAT_SHAPES, board_kinds_p=(0.75, 0.25, 0.0), samples=samples, sensor=sensor)


@dataclass
class SequencePlan:
    """Everything a sequence shows, before rendering.

    Attributes:
        static: the scene of the lit frames (rendered once, at 4x samples).
        frames: one spec per frame, with that frame's ``lux`` and ``exposure_s``.
        own_render: per frame, True when it needs its own render (shadow / shake frames);
            False when it is the static render exposed at its lux.
        attempt: the scene draw that passed the view checks.
    """

    sequence: Sequence
    static: SceneSpec
    frames: list[SceneSpec]
    own_render: list[bool]
    attempt: int

    @property
    def renders(self) -> int:
        return 1 + sum(self.own_render)


def scene_rng(seed: int, number: int, attempt: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), int(number), int(attempt)])


def noise_rng(seed: int, number: int, attempt: int, frame: int) -> np.random.Generator:
    # Five words: never the same stream as a scene's three (SeedSequence pads short entropy with zeros).
    return np.random.default_rng([int(seed), int(number), int(attempt), 1, int(frame)])


def board_outline(board: BoardSpec) -> np.ndarray:
    """(4, 3) board-frame corners of the square grid (the markers lie inside it)."""
    w, h = board.size_m
    return np.array([[0.0, 0.0, 0.0], [w, 0.0, 0.0], [w, h, 0.0], [0.0, h, 0.0]])


def board_in_view(board: BoardSpec, spec: SceneSpec, margin_px: float = VIEW_MARGIN_PX) -> bool:
    """True when the board's grid lies in front of the camera and ``margin_px`` inside the image
    at the start, centre and end of the shutter."""
    for pose in spec.trajectory:
        rvec, tvec = board_pose_in_camera(pose, spec.board_matrix)
        rotation, _ = cv2.Rodrigues(rvec)
        if np.any((board_outline(board) @ rotation.T + tvec)[:, 2] < 0.05):
            return False
        points, _ = cv2.projectPoints(board_outline(board), rvec, tvec, spec.K, None)
        points = points.reshape(-1, 2)
        if (points.min() < margin_px or np.any(points[:, 0] > spec.width - 1 - margin_px)
                or np.any(points[:, 1] > spec.height - 1 - margin_px)):
            return False
    return True


def _board_frame(spec: SceneSpec, board: BoardSpec) -> tuple[np.ndarray, np.ndarray, float]:
    """(centre (3,), normal (3,) towards the printed side, diagonal in m) of the board in the world."""
    w, h = board.size_m
    centre = spec.board_matrix[:3, :3] @ np.array([w / 2.0, h / 2.0, 0.0]) + spec.board_matrix[:3, 3]
    return centre, -spec.board_matrix[:3, 2], math.hypot(w, h)


def _sight_lines(spec: SceneSpec, board: BoardSpec, n: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """(eye (3,), points (M, 3)): the camera centre and board points spanning the grid, in the world."""
    w, h = board.size_m
    u, v = np.meshgrid(np.linspace(0.0, w, n), np.linspace(0.0, h, n))
    local = np.column_stack([u.ravel(), v.ravel(), np.zeros(u.size)])
    return spec.camera_matrix[:3, 3], local @ spec.board_matrix[:3, :3].T + spec.board_matrix[:3, 3]


def _distance_to_segments(points: np.ndarray, eye: np.ndarray, ends: np.ndarray) -> float:
    """Smallest distance from any of ``points`` (P, 3) to the segments eye -> ends[j] (M, 3)."""
    direction = ends - eye  # (M, 3)
    t = np.clip(((points[:, None, :] - eye) * direction[None]).sum(-1) / (direction**2).sum(-1)[None], 0.0, 1.0)
    closest = eye + t[..., None] * direction[None]
    return float(np.linalg.norm(points[:, None, :] - closest, axis=-1).min())


def _shadow_plan(rng: np.random.Generator, spec: SceneSpec, board: BoardSpec, n_frames: int):
    """(static spec with the spotlight, per-condition-frame specs with the caster), or None when no
    caster path keeps clear of the camera's view of the board in `MAX_DRAWS` draws."""
    centre, normal, diag = _board_frame(spec, board)
    eye, targets = _sight_lines(spec, board)
    towards_camera = (eye - centre) - ((eye - centre) @ normal) * normal
    away = -unit_vector(towards_camera) if np.linalg.norm(towards_camera) > 1e-6 else spec.board_matrix[:3, 0]
    lux = float(math.exp(rng.uniform(*np.log(SHADOW_LUX))))
    for _ in range(MAX_DRAWS):
        # The lamp on the far side of the normal from the camera, so the caster stays out of view.
        twist, _ = cv2.Rodrigues(normal * math.radians(rng.uniform(-40.0, 40.0)))
        elevation = math.radians(rng.uniform(25.0, 50.0))
        distance = rng.uniform(0.5, 1.2)
        position = centre + distance * (math.cos(elevation) * normal + math.sin(elevation) * (twist @ away))
        irradiance = spec.world.strength * rng.uniform(40.0, 100.0)  # the world light only fills the shadow
        lamp = Light("SPOT", aim_lamp(position, centre), power=irradiance * 4 * math.pi * distance**2, color=(1.0, 1.0, 1.0),
                     size=float(rng.uniform(0.003, 0.02)),
                     spot_size_deg=math.degrees(2 * math.atan(0.75 * diag / distance)) + 25.0, spot_blend=0.3)
        kind = ("rod", "ball", "box")[rng.integers(3)]
        height = rng.uniform(0.3, 0.6)  # the caster's place on the way from the board to the lamp
        width = rng.uniform(0.3, 0.55) * diag * (1.0 - height)  # its shadow: (0.3-0.55) board diagonals
        angle = rng.uniform(0.0, 2 * math.pi)
        in_plane = unit_vector(np.cross(normal, away))
        travel = math.cos(angle) * away + math.sin(angle) * in_plane  # the shadow's path on the board
        surface = sample_surface(rng)
        tumble, _ = cv2.Rodrigues(unit_vector(rng.normal(size=3)) * rng.uniform(0, math.pi))
        count = n_frames - LIT_FRAMES
        shapes, clear = [], True
        for s in np.linspace(-1.0, 1.0, count) if count > 1 else [0.0]:
            shadow_centre = centre + s * 0.85 * diag * travel
            place = shadow_centre + height * (position - shadow_centre)
            if kind == "rod":  # an arm across the light: long, across the shadow's path
                along = unit_vector(np.cross(normal, travel))
                rotation = np.column_stack([travel, np.cross(along, travel), along])
                matrix = rigid(rotation, place) @ np.diag([width, width, 3.0 * diag, 1.0])
                samples = place + np.linspace(-1.5, 1.5, 200)[:, None] * diag * along
                radius = width / math.sqrt(2)  # the box's half cross-section diagonal
            else:
                matrix = rigid(tumble, place) @ np.diag([width, width, width, 1.0])
                samples, radius = place[None], width * (0.5 if kind == "ball" else math.sqrt(3) / 2)
            if _distance_to_segments(samples, eye, targets) < radius + 0.005:
                clear = False
                break
            shapes.append(Shape("icosphere" if kind == "ball" else "cube", matrix, surface, "shadow-caster"))
        if not clear:
            continue
        tags = {**spec.tags, "lamps": 1, "spot": True, "shadow_caster": False}
        static = replace(spec, lights=[lamp], lux=lux, tags=tags)
        condition = [replace(static, shapes=spec.shapes + [caster], render_seed=int(rng.integers(0, 2**31 - 1)),
                             tags={**tags, "shadow_caster": True}) for caster in shapes]
        return static, condition
    return None


def _shake(rng: np.random.Generator) -> Callable[[float], tuple[np.ndarray, np.ndarray]]:
    """A hand-held shake: t (s) -> (rotation vector (3,) about the camera's axes, offset (3,) m in
    the camera frame), both zero at t = 0 (the rest pose). Sums of sinusoids whose peak angular speed
    is `MOTION_PEAK_RAD_S`."""
    peak = rng.uniform(*MOTION_PEAK_RAD_S)
    axes = np.stack([unit_vector(rng.normal(size=3)) for _ in range(3)])
    freq = rng.uniform(3.0, 7.0, size=3)  # Hz: physiological tremor and hand sway
    phase = rng.uniform(0.0, 2 * math.pi, size=3)
    amplitude = peak * rng.uniform(0.4, 1.0, size=3) / math.sqrt(3) / (2 * math.pi * freq)
    shifts = np.stack([unit_vector(rng.normal(size=3)) for _ in range(2)])
    shift_freq = rng.uniform(2.0, 5.0, size=2)
    shift_phase = rng.uniform(0.0, 2 * math.pi, size=2)
    shift_amplitude = rng.uniform(0.01, 0.05, size=2) / (2 * math.pi * shift_freq)  # 1-5 cm/s

    def at(t: float) -> tuple[np.ndarray, np.ndarray]:
        angles = amplitude * (np.sin(2 * math.pi * freq * t + phase) - np.sin(phase))
        offsets = shift_amplitude * (np.sin(2 * math.pi * shift_freq * t + shift_phase) - np.sin(shift_phase))
        return angles @ axes, offsets @ shifts

    return at


def _motion_plan(rng: np.random.Generator, spec: SceneSpec, board: BoardSpec, n_frames: int, sensor: SensorParams):
    """(static spec, per-condition-frame shaken specs), or None when no shake in `MAX_DRAWS` draws
    keeps the board in view."""
    lux = float(math.exp(rng.uniform(*np.log(MOTION_LUX))))
    exposure_s = exposure_time_for(lux, spec.board_look, sensor)
    static = replace(spec, lux=lux, exposure_s=exposure_s)
    rest = spec.camera_matrix
    for _ in range(MAX_DRAWS):
        shake = _shake(rng)
        condition = []
        for k in range(LIT_FRAMES, n_frames):
            centre_time = (k - LIT_FRAMES + 1) / FPS
            poses = []
            for t in (centre_time - exposure_s / 2, centre_time, centre_time + exposure_s / 2):
                rotation_vector, offset = shake(t)
                pose = rest.copy()
                pose[:3, :3] = rest[:3, :3] @ cv2.Rodrigues(rotation_vector)[0]
                pose[:3, 3] = rest[:3, 3] + rest[:3, :3] @ offset
                poses.append(pose)
            condition.append(replace(static, trajectory=np.stack(poses), tags={**spec.tags, "shake": True}))
        if all(board_in_view(board, c) for c in condition):
            return static, [replace(c, render_seed=int(rng.integers(0, 2**31 - 1))) for c in condition]
    return None


def plan_sequence(sequence: Sequence, seed: int, n_frames: int, board: BoardSpec, config: SceneConfig,
                  attempt: int) -> SequencePlan | None:
    """The scene and per-frame specs of ``sequence`` for one ``attempt``, or None when that draw fails
    the geometric checks (board out of view, caster in the way). Pure function of its arguments."""
    rng = scene_rng(seed, sequence.number, attempt)
    spec = sample_scene(rng, board.size_m, config)
    if not board_in_view(board, spec):
        return None
    if sequence.kind == "lux":
        static, condition = spec, [spec] * (n_frames - LIT_FRAMES)
        lux = [max(sequence.level, LIT_LUX)] * LIT_FRAMES + [sequence.level] * (n_frames - LIT_FRAMES)
    else:
        planned = (_shadow_plan(rng, spec, board, n_frames) if sequence.kind == "shadow"
                   else _motion_plan(rng, spec, board, n_frames, config.sensor))
        if planned is None:
            return None
        static, condition = planned
        lux = [static.lux] * n_frames
    # Exposure time: what a webcam's auto-exposure picks for this light (`expose` then sets the gain
    # on the frame itself, as the webcam adapts); a shaken frame's is the one its blur was rendered with.
    frames = [replace(base, lux=lux[k], exposure_s=exposure_time_for(lux[k], static.board_look, config.sensor))
              for k, base in enumerate([static] * LIT_FRAMES + condition)]
    own = [False] * LIT_FRAMES + [sequence.kind != "lux"] * (n_frames - LIT_FRAMES)
    static = replace(static, samples=static.samples * STATIC_SAMPLES_FACTOR, denoise=True)
    return SequencePlan(sequence=sequence, static=static, frames=frames, own_render=own, attempt=attempt)


def _shadow_fraction(shot: LabelledRender, static: LabelledRender) -> float:
    """Fraction of the lit frames' white-paper pixels that get less than half their light."""
    mask = static.white_mask
    if mask is None or mask.sum() < 20:
        return 0.0
    ratio = shot.luminance[mask] / np.maximum(static.luminance[mask], 1e-12)
    return float(np.mean(ratio < 0.5))


def make_sequence(sequence: Sequence, seed: int, n_frames: int, board: BoardSpec, config: SceneConfig, *,
                  threads: int = 0, device: str = "cpu", progress: Callable[[int], None] = report_progress) -> list[FrameLabels]:
    """Render the ``n_frames`` frames of ``sequence`` (see the module docstring).

    ``progress(units)`` is called after every render: 1 for a frame's own render, `STATIC_SAMPLES_FACTOR`
    for the shared lit render (about its cost). Raises DeepCharucoError when no scene in
    `MAX_ATTEMPTS` draws shows the whole board unoccluded (an image far too small)."""
    for attempt in range(MAX_ATTEMPTS):
        plan = plan_sequence(sequence, seed, n_frames, board, config, attempt)
        if plan is None:
            continue
        static = render_labelled(plan.static, board, threads=threads, device=device)
        progress(STATIC_SAMPLES_FACTOR)
        if static.visible.all():  # clutter can stand in the way: only the ray casts tell
            break
    else:
        raise DeepCharucoError(f"{sequence.name}: no scene in {MAX_ATTEMPTS} draws shows the whole board unoccluded "
                               f"at {config.width}x{config.height}: use a larger --width/--height")
    frames = []
    for k, spec in enumerate(plan.frames):
        if plan.own_render[k]:
            shot = render_labelled(spec, board, threads=threads, device=device)
            progress(1)
        else:
            shot = static
        # One light scale for the whole sequence, from the lit render: a frame's own median would
        # brighten a shadowed board back to the nominal lux.
        scale = luminance_scale(static.luminance, replace(plan.static, lux=spec.lux), static.white_mask)
        image, exposure = expose(shot.luminance.astype(np.float64) * scale, spec.exposure_s,
                                 noise_rng(seed, sequence.number, plan.attempt, k), config.sensor)
        meta = {
            "seed": int(seed), "frame": k, "sequence": sequence.name, "sequence_number": sequence.number,
            "sequence_frame": k, "condition": sequence.kind, "lit": k < LIT_FRAMES, "scene_attempt": plan.attempt,
            "shadow_fraction": _shadow_fraction(shot, static) if plan.own_render[k] and sequence.kind == "shadow" else 0.0,
            **scene_meta(board, replace(spec, samples=shot.spec.samples), shot.visible, config.sensor, exposure),
        }
        frames.append(FrameLabels(image=image, corners=shot.corners, visible=shot.visible, K=spec.K.astype(np.float32),
                                  rvec=shot.rvec, tvec=shot.tvec, meta=meta))
    return frames


@dataclass(frozen=True)
class SceneJob:
    """What one run of a rendered evaluation set renders (everything a worker needs, picklable); subclasses
    name their ``command``."""

    command: ClassVar[str]
    out: str
    seed: int
    frames: int
    board: BoardSpec
    width: int
    height: int
    samples: int
    device: str
    threads: int

    def content(self) -> dict:
        """The arguments that decide pixels and labels: a resumed run must agree on all of them."""
        return {"command": self.command, "seed": self.seed, "frames": self.frames, "board": self.board.to_dict(),
                "width": self.width, "height": self.height, "samples": self.samples}


@dataclass(frozen=True)
class SequenceJob(SceneJob):
    """A run of the paper's 26 sequences."""

    command: ClassVar[str] = "evaluate.paper.sequences"

    def generator(self, sequence: Sequence) -> dict:
        return {"package": "deepcharuco", "version": deepcharuco.__version__, "command": "evaluate.paper.sequences",
                "args": self.content(), "sequence": sequence.name, "device": self.device}

    def config(self) -> SceneConfig:
        return evaluation_config(self.width, self.height, self.samples)


def render_sequence(job: SequenceJob, number: int) -> int:
    """Render sequence ``number`` and write it as shard ``number``; returns its frame count."""
    sequence = SEQUENCES[number]
    frames = make_sequence(sequence, job.seed, job.frames, job.board, job.config(), threads=job.threads, device=job.device)
    write_shard(job.out, number, frames, job.board, job.generator(sequence))
    return len(frames)


def estimated_work(sequence: Sequence, n_frames: int) -> int:
    """The progress bar's units of work in a sequence (when its first scene draw passes): one per
    frame render, `STATIC_SAMPLES_FACTOR` for the shared lit render (its cost, measured)."""
    return STATIC_SAMPLES_FACTOR + (0 if sequence.kind == "lux" else n_frames - LIT_FRAMES)


def run(job: SequenceJob, selected: list[Sequence], *, resume: bool, workers: int = 1, quiet: bool = False) -> dict:
    """Render the selected sequences missing from ``job.out``; returns index.json's content."""
    numbers = [s.number for s in selected]
    out = output_folder(job.out)  # a writable folder, before anything is rendered
    done = check_existing(job, numbers, resume)
    todo = [s for s in selected if s.number not in done]
    remove_stale_temporaries(out, [s.number for s in todo])
    # Longest first: with several workers the shake and shadow sequences should not start last.
    todo.sort(key=lambda s: -estimated_work(s, job.frames))
    total = sum(estimated_work(s, job.frames) for s in todo)
    if not quiet:
        skipped = len(selected) - len(todo)
        print(f"evaluate.paper.sequences: {len(todo)} sequence(s) of {job.frames} frames to render into {out}"
              + (f" ({skipped} already there)" if skipped else "")
              + f"; progress in frame renders, a shared lit render counting {STATIC_SAMPLES_FACTOR}", file=sys.stderr)
    run_shard_tasks(render_sequence, [(job, s.number) for s in todo], [s.number for s in todo], out, noun="sequence",
                    total=total, unit="render", workers=workers, tasks_per_child=8, quiet=quiet)
    return update_index(out)


def select(names: list[str] | None) -> list[Sequence]:
    """The sequences named (all when None), in number order; DeepCharucoError names unknown ones."""
    if not names:
        return list(SEQUENCES)
    unknown = [n for n in names if n not in SEQUENCE_NAMES]
    if unknown:
        raise DeepCharucoError(f"unknown sequence(s) {', '.join(unknown)}: --only takes names from "
                               f"{', '.join(SEQUENCE_NAMES)}")
    return [s for s in SEQUENCES if s.name in set(names)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m evaluate.paper.sequences", formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description="Render twins of the paper's 26 evaluation videos (a static board, a still camera: 10 light levels "
                    "x 2 scenes, 3 moving shadows, 3 camera shakes), one HDF5 shard per sequence.",
        epilog=f"Sequences (shard index = position): {', '.join(SEQUENCE_NAMES)}.")
    parser.add_argument("--out", default="data/sequences", help="output folder of shard-*.h5 + index.json")
    parser.add_argument("--frames", type=int, default=60,
                        help=f"frames per sequence: {LIT_FRAMES} well-lit static frames, then the condition")
    parser.add_argument("--seed", type=int, default=0, help="run seed: each sequence depends only on (seed, its number, arguments)")
    parser.add_argument("--samples", type=int, default=4,
                        help=f"Cycles samples per pixel of a frame's render (the shared lit render: {STATIC_SAMPLES_FACTOR}x)")
    parser.add_argument("--only", nargs="+", metavar="NAME", default=None, help="render only these sequences (e.g. lux-0.3-a motion-1)")
    parser.add_argument("--resume", action="store_true", help="continue a run in --out, rendering only missing sequences")
    parser.add_argument("--width", type=int, default=320, help="image width in pixels")
    parser.add_argument("--height", type=int, default=240, help="image height in pixels")
    parser.add_argument("--board", default=None, help="BoardSpec .json/.yaml file (default: the paper's 5x5 DICT_5X5_50 board)")
    parser.add_argument("--workers", type=int, default=1, help="parallel local render processes (one sequence each)")
    parser.add_argument("--threads", type=int, default=0, help="Cycles threads per worker (0: cores / workers)")
    parser.add_argument("--device", choices=("cpu", "gpu"), default="cpu", help="Cycles device (gpu: CUDA/OptiX/...)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)

    problems = [f"--{name} must be >= {low}, got {getattr(args, name)}"
                for name, low in (("frames", LIT_FRAMES + 1), ("samples", 1), ("width", 64), ("height", 48),
                                  ("workers", 1), ("threads", 0), ("seed", 0))
                if getattr(args, name) < low]
    if problems:
        parser.error("; ".join(problems) + (f" (the first {LIT_FRAMES} frames are the well-lit start)"
                                            if args.frames <= LIT_FRAMES else ""))
    def body() -> None:
        selected = select(args.only)
        board = BoardSpec.load(args.board) if args.board else BoardSpec()
        threads = args.threads or max(1, (os.cpu_count() or 1) // args.workers)
        job = SequenceJob(out=args.out, seed=args.seed, frames=args.frames, board=board, width=args.width,
                          height=args.height, samples=args.samples, device=args.device, threads=threads)
        started = time.perf_counter()
        index = run(job, selected, resume=args.resume, workers=args.workers, quiet=args.quiet)
        if not args.quiet:
            print(f"evaluate.paper.sequences: {index['frames']} frame(s) in {len(index['shards'])} sequence(s) in "
                  f"{args.out} ({time.perf_counter() - started:.0f} s)", file=sys.stderr)

    return run_command(body)


if __name__ == "__main__":
    sys.exit(main())
