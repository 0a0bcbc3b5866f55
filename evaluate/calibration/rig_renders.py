"""``python -m evaluate.calibration.rig_renders``: Blender renders of a board waved through a rig of cameras, with exact truth.

The rig and the board's poses are `evaluate.calibration.rig_views`' for the same seed (the same cameras, lenses and waving);
each view is rendered by Cycles through its camera's lens (`datagen.frames.render_labelled`: a wider pinhole render
resampled through the distortion, so a corner lies where ``cv2.projectPoints`` puts it) in a room with lamps and a
matte or glossy print (`evaluate.calibration.calibration_sequences.calibration_config`), then taken by the sensor model
(`datagen.sensor`: photon and read noise, auto-exposure, 8 bits):

- ``good``: 400 lux on the board;
- ``1lux``: the same renders at 1 lux (the sensor's gain and noise: what a dim lab gives);
- ``shake``: the board moving 0.5-1.5 m/s and turning 1-3 rad/s during the exposure (auto-exposure at 60-200 lux:
  13-33 ms), rendered with its motion blur, labelled at the shutter's centre.

Writes ``OUT/<condition>/cam<c>/<instant>.png`` (the folders `deepcharuco calibrate` takes as a rig's sources) and
``OUT/truth.json`` (per camera K, dist, R, t with x_cam = R X + t in camera 0's frame, metres; the board). Resumes:
views whose images exist are not rendered again. Every random choice comes from ``--seed``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from deepcharuco.boards.board import BoardSpec
from deepcharuco.cli.common import output_folder, run_command
from evaluate.calibration.calibration_sequences import DARK_LUX, GOOD_LUX, calibration_config
from evaluate.calibration.rig_views import RIG_BOARD, board_poses, rig_cameras

CONDITIONS = ("good", "1lux", "shake")
SPEED_M_S = (0.5, 1.5)
TURN_RAD_S = (1.0, 3.0)


def _transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = R, t
    return out


def plan(board: BoardSpec, seed: int, cameras: int, instants: int, size: tuple[int, int]) -> dict:
    """The rig, the board's poses and motion, the scene and every render's seed: all drawn before any render, so a
    resumed run draws the same."""
    from datagen.scene import sample_scene
    from evaluate.paper.sequences import MOTION_LUX

    rng = np.random.default_rng(seed)  # `evaluate.calibration.rig_views.drawn_rig`'s draws, in its order
    intrinsics, rotations, translations, target = rig_cameras(rng, cameras, size)
    board_r, board_t = board_poses(rng, board, target, instants)
    more = np.random.default_rng([seed, 7])
    scene = sample_scene(more, board.size_m, calibration_config(*size, 8))
    scene = replace(scene, shapes=[s for s in scene.shapes if s.role == "room"][:1], denoise=True)
    directions = more.normal(size=(instants, 2, 3))
    directions /= np.linalg.norm(directions, axis=2, keepdims=True)
    velocity = directions[:, 0] * more.uniform(*SPEED_M_S, (instants, 1))
    spin = directions[:, 1] * more.uniform(*TURN_RAD_S, (instants, 1))
    seeds = more.integers(0, 2**31 - 1, (cameras, instants, 2))
    shake_lux = float(math.exp(more.uniform(*np.log(MOTION_LUX))))
    return {"cameras": intrinsics, "rotations": rotations, "translations": translations, "board_r": board_r,
            "board_t": board_t, "scene": scene, "velocity": velocity, "spin": spin, "seeds": seeds,
            "shake_lux": shake_lux, "centre": np.array([board.size_m[0] / 2, board.size_m[1] / 2, 0.0])}


def _board_at(p: dict, n: int, dt: float) -> np.ndarray:
    """(4, 4) board -> camera 0's frame at instant n plus dt seconds (turning about the board's centre)."""
    R, t = p["board_r"][n], p["board_t"][n]
    turn = cv2.Rodrigues(p["spin"][n] * dt)[0]
    centre = R @ p["centre"] + t
    return _transform(turn @ R, turn @ (t - centre) + centre + p["velocity"][n] * dt)


def render_view(board: BoardSpec, p: dict, c: int, n: int, conditions: list[str], threads: int) -> dict[str, np.ndarray]:
    """Camera c's images of instant n under each condition."""
    from datagen.frames import expose, luminance_scale, render_labelled
    from datagen.scene import exposure_time_for
    from datagen.sensor import SensorParams

    camera, scene, sensor = p["cameras"][c], p["scene"], SensorParams()
    rig = _transform(p["rotations"][c], p["translations"][c])
    width, height = camera.image_size
    images = {}

    def world(dt: float) -> np.ndarray:  # world from OpenCV camera: the board stays, the camera moves around it
        return scene.board_matrix @ np.linalg.inv(rig @ _board_at(p, n, dt))

    if any(condition != "shake" for condition in conditions):
        spec = replace(scene, K=camera.K, width=width, height=height, trajectory=np.stack([world(0.0)] * 3),
                       render_seed=int(p["seeds"][c, n, 0]))
        shot = render_labelled(spec, board, threads=threads, dist=camera.dist)
        for index, (condition, lux) in enumerate((("good", GOOD_LUX), ("1lux", DARK_LUX))):
            if condition in conditions:
                lit = replace(spec, lux=lux, exposure_s=exposure_time_for(lux, spec.board_look, sensor))
                scale = luminance_scale(shot.luminance, lit, shot.white_mask)
                noise = np.random.default_rng([int(p["seeds"][c, n, 0]), index])
                images[condition] = expose((shot.luminance * scale).astype(np.float64), lit.exposure_s, noise, sensor)[0]
    if "shake" in conditions:
        lux = p["shake_lux"]
        exposure_s = exposure_time_for(lux, scene.board_look, sensor)
        spec = replace(scene, K=camera.K, width=width, height=height, lux=lux, exposure_s=exposure_s,
                       trajectory=np.stack([world(dt) for dt in (-exposure_s / 2, 0.0, exposure_s / 2)]),
                       render_seed=int(p["seeds"][c, n, 1]))
        shot = render_labelled(spec, board, threads=threads, dist=camera.dist)
        scale = luminance_scale(shot.luminance, spec, shot.white_mask)
        noise = np.random.default_rng([int(p["seeds"][c, n, 1]), 2])
        images["shake"] = expose((shot.luminance * scale).astype(np.float64), exposure_s, noise, sensor)[0]
    return images


def truth(board: BoardSpec, p: dict, seed: int) -> dict:
    return {"seed": seed, "board": board.to_dict(), "shake_lux": p["shake_lux"],
            "cameras": [{"K": camera.K.tolist(), "dist": camera.dist.tolist(), "image_size": list(camera.image_size),
                         "R": R.tolist(), "t": t.tolist()}
                        for camera, R, t in zip(p["cameras"], p["rotations"], p["translations"])]}


def run(board: BoardSpec, out: Path, *, seed: int, cameras: int, instants: int, size: tuple[int, int],
        conditions: list[str], threads: int = 0, quiet: bool = False) -> int:
    """Render what is missing under ``out``; returns the views rendered."""
    p = plan(board, seed, cameras, instants, size)
    record = truth(board, p, seed)
    truth_path = out / "truth.json"
    if truth_path.is_file() and json.loads(truth_path.read_text()) != json.loads(json.dumps(record)):
        raise SystemExit(f"error: {truth_path} holds another rig (seed, board or size): give another --out")
    truth_path.write_text(json.dumps(record, indent=1))
    todo = [(c, n) for c in range(cameras) for n in range(instants)
            if not all((out / condition / f"cam{c}" / f"{n:03d}.png").is_file() for condition in conditions)]
    for c, n in tqdm(todo, desc="rendering", unit="view", disable=quiet):
        for condition, image in render_view(board, p, c, n, conditions, threads).items():
            folder = out / condition / f"cam{c}"
            folder.mkdir(parents=True, exist_ok=True)
            temporary = folder / f".{n:03d}.tmp.png"
            cv2.imwrite(str(temporary), image)
            temporary.replace(folder / f"{n:03d}.png")
    return len(todo)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m evaluate.calibration.rig_renders", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--out", default="data/rig_renders", help="folder of the renders and truth.json")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--cameras", type=int, default=3)
    parser.add_argument("--instants", type=int, default=40)
    parser.add_argument("--size", default="640x480")
    parser.add_argument("--conditions", nargs="+", choices=CONDITIONS, default=list(CONDITIONS))
    parser.add_argument("--board", default=None, help="board file (default: evaluate.calibration.rig_views.RIG_BOARD)")
    parser.add_argument("--threads", type=int, default=0, help="Cycles threads (0: all cores)")
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    if args.cameras < 2 or args.instants < 6:
        parser.error("a rig needs --cameras >= 2 and --instants >= 6")
    try:
        size = tuple(int(v) for v in args.size.lower().split("x"))
    except ValueError:
        parser.error(f"--size is WIDTHxHEIGHT, e.g. 640x480, got {args.size!r}")
    board = BoardSpec.load(args.board) if args.board else RIG_BOARD

    def body() -> None:
        out = output_folder(args.out)
        done = run(board, out, seed=args.seed, cameras=args.cameras, instants=args.instants, size=size,
                   conditions=args.conditions, threads=args.threads, quiet=args.quiet)
        print(f"{done} views rendered -> {out}/")

    return run_command(body)


if __name__ == "__main__":
    sys.exit(main())
