"""``python -m evaluate.calibration.fisheye_rig_eval``: fisheye rigs (~180 degree lenses) calibrated against exact truth.

Drawn rigs (`evaluate.calibration.fisheye_views`: 3 cameras, OpenCV's fisheye model, exact views) in good light and
dark, through the CLI's solve (`deepcharuco.cli.calibrate_rig.solve_rig` with ``model="fisheye"``: each camera's
own ``cv2.fisheye`` calibration, then the rig's bundle adjustment), per detector: each camera's rotation error
(degrees) and centre error (mm per metre of the rig's baseline), each lens parameter's error over its reported
deviation, and the corners the detector found against those the view shows, by the ray's angle off the lens's
axis (the image circle's edge is 90 degrees). Nothing here was tuned on: these rigs only measure.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from deepcharuco.calibration.rig_model import RigResult
from deepcharuco.calibration.views import CalibrationError, FrameDetection, SelectionOptions, border_margin
from deepcharuco.cli.calibrate_rig import solve_rig
from evaluate.calibration.fisheye_views import FISHEYE_BOARD, drawn_fisheye_rig
from evaluate.calibration.rig_eval import DETECTORS, detect_all, make_detector, truth_errors
from evaluate.calibration.rig_views import DrawnRig

CONDITIONS = ("good", "dark")
ANGLE_BINS = (0.0, 30.0, 60.0, 75.0, 85.0, 90.0)  # degrees off the lens's axis
PARAMETERS = ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")


def lens_errors(result: RigResult, truth: DrawnRig) -> list[dict[str, float]]:
    """Per camera, each lens parameter's error (solved - true) over its reported standard deviation."""
    out = []
    for c, camera in enumerate(truth.cameras):
        solved = result.cameras[c]
        values = lambda cam: dict(zip(PARAMETERS, [cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2], *cam.dist]))  # noqa: E731
        mine, true = values(solved), values(camera)
        out.append({name: (mine[name] - true[name]) / result.std[c][name] if result.std[c].get(name) else math.nan
                    for name in PARAMETERS})
    return out


def corners_by_angle(truth: DrawnRig, visible: list[list[np.ndarray]], detections: list[list[FrameDetection]]
                     ) -> list[dict]:
    """Corners the views show and the detector found (its IDs among those shown), per bin of `ANGLE_BINS`."""
    points = truth.board.object_points()
    shown = np.zeros(len(ANGLE_BINS) - 1, int)
    found = np.zeros(len(ANGLE_BINS) - 1, int)
    for c, (R, t) in enumerate(zip(truth.rotations, truth.translations)):
        for n, ids in enumerate(visible[c]):
            if len(ids) == 0:
                continue
            in_camera = points[ids] @ (R @ truth.board_rotations[n]).T + R @ truth.board_translations[n] + t
            angle = np.degrees(np.arctan2(np.hypot(in_camera[:, 0], in_camera[:, 1]), in_camera[:, 2]))
            bins = np.clip(np.digitize(angle, ANGLE_BINS) - 1, 0, len(shown) - 1)
            hit = np.isin(ids, detections[c][n].ids)
            np.add.at(shown, bins, 1)
            np.add.at(found, bins, hit.astype(int))
    return [{"degrees": f"{ANGLE_BINS[k]:g}-{ANGLE_BINS[k + 1]:g}", "shown": int(shown[k]), "found": int(found[k])}
            for k in range(len(shown))]


def experiment(seeds: list[int], conditions: list[str], instants: int, detectors: list[str], size: tuple[int, int],
               quiet: bool) -> list[dict]:
    rows = []
    for seed in seeds:
        for condition in conditions:
            truth, visible = drawn_fisheye_rig(seed=seed, instants=instants, size=size, condition=condition)
            names = [f"cam{c}" for c in range(len(truth.cameras))]
            sizes = [camera.image_size for camera in truth.cameras]
            for name in detectors:
                detector, refine = make_detector(name, FISHEYE_BOARD)
                started = time.perf_counter()
                detections = detect_all(truth.frames, detector, quiet, f"seed {seed} {condition} {name}")
                row = {"seed": seed, "condition": condition, "detector": name, "size": list(size),
                       "views_detected": [sum(len(f.ids) >= 6 for f in camera) for camera in detections],
                       "corners_by_angle": corners_by_angle(truth, visible, detections)}
                try:
                    result = solve_rig([[frames] for frames in detections], sizes, names, [FISHEYE_BOARD],
                                       SelectionOptions(border_px=border_margin(refine)), model="fisheye")
                except CalibrationError as error:
                    row["failed"] = str(error)
                else:
                    row.update(truth_errors(result, truth))
                    ratios = lens_errors(result, truth)
                    row["lens_error_over_std"] = ratios
                    row["worst_lens_error_over_std"] = max(abs(v) for r in ratios for v in r.values())
                    row["notes"] = result.notes
                row["seconds"] = time.perf_counter() - started
                rows.append(row)
                if not quiet:
                    print(_line(row), flush=True)
    return rows


def _line(row: dict) -> str:
    head = f"seed {row['seed']} {row['condition']:5s} {row['detector']:6s} views {row['views_detected']}"
    corners = ", ".join(f"{b['degrees']} deg {b['found']}/{b['shown']}" for b in row["corners_by_angle"])
    if "failed" in row:
        return f"{head}: no rig ({row['failed']}); corners found/shown {corners}"
    w = row["worst"]
    return (f"{head}: worst rotation {w['rotation_deg']:.3f} deg, centre {w['centre_mm_per_m']:.2f} mm/m, lens "
            f"error / deviation <= {row['worst_lens_error_over_std']:.2f}, RMS {row['rms_px']:.3f} px, shared "
            f"{row['shared']}; corners found/shown {corners}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m evaluate.calibration.fisheye_rig_eval",
                                     description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--conditions", nargs="+", choices=CONDITIONS, default=list(CONDITIONS))
    parser.add_argument("--instants", type=int, default=50, help="instants (board poses) per drawn rig")
    parser.add_argument("--size", type=int, nargs=2, default=[1024, 768], metavar=("W", "H"))
    parser.add_argument("--detectors", nargs="+", choices=DETECTORS, default=list(DETECTORS))
    parser.add_argument("--out", type=Path, default=Path("report/fisheye_rig_eval.json"))
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    if args.instants < 10 or min(args.size) < 200:
        parser.error("--instants must be >= 10 and --size at least 200 x 200")
    rows = experiment(args.seeds, args.conditions, args.instants, args.detectors, tuple(args.size), args.quiet)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(rows, indent=1))
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
