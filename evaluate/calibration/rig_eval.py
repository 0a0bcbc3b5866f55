"""``python -m evaluate.calibration.rig_eval``: rig calibration measured against truth, the deep detector beside OpenCV's.

Two kinds of data:

- drawn rigs (`evaluate.calibration.rig_views`: exact truth of every camera's intrinsics, distortion and pose), in good light,
  dark and under shake: per detector, each camera's rotation error (degrees) and centre error (mm per metre of the
  rig's baseline) against the truth, fx/fy error (%), and the views and shared instants kept; with ``--rendered``
  the same of Blender-rendered rigs (`evaluate.calibration.rig_renders`: good light, 1 lux, shake);
- with ``--realdata DIR``, the four synchronised caliscope webcams (``DIR/caliscope_calibration``; no truth of the
  extrinsics exists): per detector the RMS per camera, the square length of the board as the rig triangulates it
  (every corner seen by two cameras or more at one instant, triangulated from all of them; neighbouring corners'
  distances against the printed 54 mm), and fx/fy against caliscope's own calibration of each camera; with ``--dark
  K`` also every frame darkened (k = K), each rig's cameras compared with the deep detector's lit rig (rotation,
  centre per metre of baseline: `rig_agreement`). Detectors: opencv, deep (the lite networks), fast (``network="fast"``).

Both detectors go through the same solver (`deepcharuco.cli.calibrate_rig.solve_rig`, the CLI's defaults). Nothing
here was tuned on: the solver's constants were set on `tests/calibration/test_rig.py`'s exact projections and seed 0's drawn
rig (good light); these seeds, the dark and shake conditions and the real videos only measure.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from deepcharuco.boards.board import BoardSpec
from deepcharuco.calibration.rig_model import RigResult, rotation_angle_deg
from deepcharuco.calibration.views import CalibrationError, FrameDetection, SelectionOptions, border_margin, sharpness
from deepcharuco.cli.calibrate_rig import solve_rig
from deepcharuco.core.opencv_api import undistort_points
from deepcharuco.geometry.camera import Camera, read_camera
from evaluate.calibration.rig_views import CONDITIONS, RIG_BOARD, DrawnRig, drawn_rig

DETECTORS = ("opencv", "deep", "fast", "auto")  # fast, auto: the deep detector with network="fast" or "auto"


def make_detector(name: str, board: BoardSpec):
    if name == "opencv":
        from deepcharuco.detection.opencv_detector import OpenCVDetector

        return OpenCVDetector(board, refine="subpix"), "subpix"
    from deepcharuco.detection.deep_detector import Detector

    return Detector(board=board, network="lite" if name == "deep" else name), "refinenet"


def detect_all(frames: list[list[np.ndarray]], detector, quiet: bool = True, label: str = "") -> list[list[FrameDetection]]:
    """Per camera, one `FrameDetection` per instant."""
    out = []
    for c, views in enumerate(frames):
        detections = []
        for n, image in enumerate(tqdm(views, desc=f"{label} camera {c}", disable=quiet, leave=False)):
            found = detector.detect(image)
            detections.append(FrameDetection(n, str(n), found.ids, found.corners, sharpness(image, found.corners),
                                             found.covariances))
        out.append(detections)
    return out


def calibrate(detections: list[list[FrameDetection]], sizes, names, board: BoardSpec, refine: str,
              given: list[str] | None = None, weigh_rig_corners: bool = True) -> tuple[RigResult | None, str]:
    """The CLI's rig solve (``given``: camera files whose intrinsics are held, as --camera; ``weigh_rig_corners``
    False: the bundle adjustment weighs every corner alike, as before 2026-11-26), or (None, why not)."""
    options = SelectionOptions(border_px=border_margin(refine))
    try:
        return solve_rig([[frames] for frames in detections], sizes, names, [board], options, given=given,
                         weigh_rig_corners=weigh_rig_corners), ""
    except CalibrationError as error:
        return None, str(error)


def truth_errors(result: RigResult, truth: DrawnRig) -> dict:
    """Per camera: rotation error (deg), centre error (mm per metre of baseline), fx / fy error (%)."""
    baseline = truth.baseline
    cameras = []
    for c, camera in enumerate(truth.cameras):
        solved = result.cameras[c]
        rotation = rotation_angle_deg(result.rotations[c] @ truth.rotations[c].T)
        centre = np.linalg.norm(result.centre(c) - (-truth.rotations[c].T @ truth.translations[c]))
        cameras.append({"rotation_deg": rotation, "centre_mm_per_m": 1000 * centre / baseline,
                        "fx_pct": 100 * (solved.K[0, 0] / camera.K[0, 0] - 1),
                        "fy_pct": 100 * (solved.K[1, 1] / camera.K[1, 1] - 1),
                        "views": result.camera_views(c), "rms_px": result.camera_rms(c),
                        "std_fx_pct": 100 * result.std[c].get("fx", math.nan) / camera.K[0, 0],
                        "std_rotation_deg": result.std[c].get("rotation_deg", 0.0),
                        "std_centre_mm_per_m": 1000 * math.sqrt(sum(result.std[c].get(k, 0.0) ** 2
                                                                    for k in ("tx", "ty", "tz"))) / baseline})
    worst = {key: max(abs(cam[key]) for cam in cameras) for key in ("rotation_deg", "centre_mm_per_m", "fx_pct", "fy_pct")}
    return {"cameras": cameras, "worst": worst, "shared": {f"{i}-{j}": n for (i, j), n in sorted(result.shared.items())},
            "baseline_m": baseline, "rms_px": result.rms, "disagreement": result.disagreement,
            "intrinsics_held": not any(result.terms)}


def triangulated_squares(result: RigResult, board: BoardSpec) -> dict:
    """Every corner seen by two cameras or more at one instant, triangulated (linear, from all of them, on
    undistorted rays); the distances between neighbouring corners of the board against its square length."""
    by_instant: dict[int, list] = {}
    for view in result.views:
        by_instant.setdefault(view.key, []).append(view)
    columns = board.squares_x - 1
    ratios = []
    for views in by_instant.values():
        if len(views) < 2:
            continue
        rays: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
        for view in views:
            camera = result.cameras[view.camera]
            normalised = undistort_points(view.corners.reshape(-1, 1, 2), camera.K, camera.dist, None,
                                          (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 50, 1e-12)).reshape(-1, 2)
            P = np.column_stack([result.rotations[view.camera], result.translations[view.camera]])
            for corner_id, xy in zip(view.ids, normalised):
                rays.setdefault(int(corner_id), []).append((P, xy))
        points = {}
        for corner_id, seen in rays.items():
            if len(seen) < 2:
                continue
            rows = []
            for P, (x, y) in seen:
                rows += [x * P[2] - P[0], y * P[2] - P[1]]
            solution = np.linalg.svd(np.array(rows))[2][-1]
            points[corner_id] = solution[:3] / solution[3]
        for corner_id, point in points.items():
            for neighbour in ((corner_id + 1) if (corner_id + 1) % columns else None, corner_id + columns):
                if neighbour is not None and neighbour in points:
                    ratios.append(float(np.linalg.norm(points[neighbour] - point)) / board.square_length)
    ratios = np.array(ratios)
    if len(ratios) == 0:
        return {"pairs": 0}
    return {"pairs": int(len(ratios)), "median_error_pct": float(100 * (np.median(ratios) - 1)),
            "mean_error_pct": float(100 * (np.mean(ratios) - 1)),
            "p90_abs_error_pct": float(100 * np.percentile(np.abs(ratios - 1), 90))}


def drawn_experiment(seeds: list[int], conditions: list[str], instants: int, detectors: list[str], quiet: bool,
                     weigh: bool = True) -> list[dict]:
    rows = []
    for seed in seeds:
        for condition in conditions:
            truth = drawn_rig(RIG_BOARD, seed=seed, instants=instants, condition=condition)
            names = [f"cam{c}" for c in range(len(truth.cameras))]
            sizes = [camera.image_size for camera in truth.cameras]
            for name in detectors:
                detector, refine = make_detector(name, RIG_BOARD)
                started = time.perf_counter()
                detections = detect_all(truth.frames, detector, quiet, f"seed {seed} {condition} {name}")
                result, why = calibrate(detections, sizes, names, RIG_BOARD, refine, weigh_rig_corners=weigh)
                row = {"seed": seed, "condition": condition, "detector": name,
                       "views_detected": [sum(len(f.ids) >= 6 for f in camera) for camera in detections],
                       "seconds": time.perf_counter() - started}
                row.update(truth_errors(result, truth) if result else {"failed": why})
                rows.append(row)
                if not quiet:
                    print(_drawn_line(row), flush=True)
    return rows


def _drawn_line(row: dict) -> str:
    head = f"seed {row['seed']} {row['condition']:5s} {row['detector']:6s} views {row['views_detected']}"
    if "failed" in row:
        return f"{head}: no rig ({row['failed']})"
    w = row["worst"]
    return (f"{head}: worst rotation {w['rotation_deg']:.3f} deg, centre {w['centre_mm_per_m']:.2f} mm/m, fx "
            f"{w['fx_pct']:.2f} %, fy {w['fy_pct']:.2f} %, RMS {row['rms_px']:.3f} px, shared {row['shared']}, "
            f"disagreement {row['disagreement']:.2f}{' (intrinsics held)' if row['intrinsics_held'] else ''}")


def rendered_experiment(folder: Path, detectors: list[str], quiet: bool, weigh: bool = True) -> list[dict]:
    """The Blender-rendered rig in ``folder`` (`evaluate.calibration.rig_renders`): each condition's views through both
    detectors and the same solve, against the truth."""
    record = json.loads((folder / "truth.json").read_text())
    board = BoardSpec.from_dict(record["board"])
    cameras = [Camera(np.array(c["K"]), np.array(c["dist"]), tuple(c["image_size"])) for c in record["cameras"]]
    rows = []
    for condition in sorted(p.name for p in folder.iterdir() if p.is_dir()):
        paths = [sorted((folder / condition / f"cam{c}").glob("[0-9]*.png")) for c in range(len(cameras))]
        # The cameras whose every instant is rendered (a render still running has done the first ones).
        complete = [c for c in range(len(cameras)) if paths[c] and len(paths[c]) == max(len(p) for p in paths)]
        if len(complete) < 2:
            continue
        frames = [[cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) for path in paths[c]] for c in complete]
        truth = DrawnRig(board, [cameras[c] for c in complete],
                         np.array([record["cameras"][c]["R"] for c in complete]),
                         np.array([record["cameras"][c]["t"] for c in complete]), np.zeros((0, 3, 3)),
                         np.zeros((0, 3)), frames)
        if complete[0] != 0:  # the rig's frame is its first camera's
            R0, t0 = truth.rotations[0].copy(), truth.translations[0].copy()
            truth.translations = truth.translations - np.einsum("cij,jk,k->ci", truth.rotations, R0.T, t0)
            truth.rotations = truth.rotations @ R0.T
        names = [f"cam{c}" for c in complete]
        for name in detectors:
            detector, refine = make_detector(name, board)
            detections = detect_all(frames, detector, quiet, f"{folder.name} {condition} {name}")
            result, why = calibrate(detections, [c.image_size for c in truth.cameras], names, board, refine,
                                    weigh_rig_corners=weigh)
            row = {"seed": record["seed"], "condition": f"rendered {condition}", "detector": name, "cameras_used": names,
                   "views_detected": [sum(len(f.ids) >= 6 for f in camera) for camera in detections]}
            row.update(truth_errors(result, truth) if result else {"failed": why})
            rows.append(row)
            if not quiet:
                print(_drawn_line(row), flush=True)
    return rows


def rig_agreement(result: RigResult, reference: RigResult) -> dict:
    """How far ``result``'s cameras sit from ``reference``'s, both seen from camera 0: per camera the rotation between
    them (deg) and the centres' distance (mm per metre of the reference's longest baseline), and the worst of each."""
    def relative(rig: RigResult, c: int) -> tuple[np.ndarray, np.ndarray]:
        return rig.rotations[c] @ rig.rotations[0].T, rig.rotations[0] @ (rig.centre(c) - rig.centre(0))

    count = len(reference.cameras)
    centres = [relative(reference, c)[1] for c in range(count)]
    baseline = max(np.linalg.norm(a - b) for a in centres for b in centres)
    cameras = []
    for c in range(count):
        (rotation, centre), (rotation_ref, centre_ref) = relative(result, c), relative(reference, c)
        cameras.append({"rotation_deg": rotation_angle_deg(rotation @ rotation_ref.T),
                        "centre_mm_per_m": 1000 * float(np.linalg.norm(centre - centre_ref)) / baseline})
    return {"cameras": cameras, "worst_rotation_deg": max(c["rotation_deg"] for c in cameras),
            "worst_centre_mm_per_m": max(c["centre_mm_per_m"] for c in cameras)}


def real_experiment(folder: Path, detectors: list[str], quiet: bool, weigh: bool = True, dark: int = 0) -> list[dict]:
    """The caliscope rig (module docstring); with ``dark`` > 0 also every frame darkened (`darken`, k = ``dark``),
    each rig compared with the deep detector's lit rig of the same intrinsics (`rig_agreement`, ``vs_lit_deep``)."""
    from evaluate.paper.protocols import darken
    from evaluate.speed.realistic import video_frames

    session = folder / "caliscope_calibration"
    board = BoardSpec.load(session / "board.yaml")
    videos = sorted(session.glob("cam_*.mp4"))
    frames = [[cv2.cvtColor(f, cv2.COLOR_BGR2GRAY) if f.ndim == 3 else f for f in video_frames(v)] for v in videos]
    names = [v.stem for v in videos]
    sizes = [(f[0].shape[1], f[0].shape[0]) for f in frames]
    theirs = [read_camera(session / f"camera_{name}.yaml") for name in names]
    given = [str(session / f"camera_{name}.yaml") for name in names]
    rows, lit_deep = [], {}  # the deep detector's lit rig per intrinsics: the dark rigs' reference
    conditions = [("lit", frames)] + ([(f"dark k={dark}", [[darken(f, dark) for f in views] for views in frames])]
                                      if dark > 0 else [])
    for (condition, seen), name in ((c, n) for c in conditions for n in detectors):
        detector, refine = make_detector(name, board)
        detections = detect_all(seen, detector, quiet, f"{name} {condition}")
        # As a user runs it (every camera's intrinsics solved), and with them held at caliscope's own calibration
        # (--camera per camera), where both detectors' corners go through the same extrinsic solve.
        for intrinsics, held in (("solved", None), ("caliscope's", given)):
            result, why = calibrate(detections, sizes, names, board, refine, held, weigh_rig_corners=weigh)
            if (name, condition) == ("deep", "lit"):
                lit_deep[intrinsics] = result
            reference = lit_deep.get(intrinsics)
            row = {"detector": name, "condition": condition, "intrinsics": intrinsics,
                   "views_detected": [sum(len(f.ids) >= 6 for f in camera) for camera in detections]}
            if result is not None and reference is not None and dark > 0:
                row["vs_lit_deep"] = rig_agreement(result, reference)
            if result is None:
                row["failed"] = why
            else:
                row.update({"rms_px": result.rms, "cameras": [
                    {"name": names[c], "rms_px": result.camera_rms(c), "views": result.camera_views(c),
                     "fx_vs_caliscope_pct": 100 * (result.cameras[c].K[0, 0] / theirs[c].K[0, 0] - 1),
                     "fy_vs_caliscope_pct": 100 * (result.cameras[c].K[1, 1] / theirs[c].K[1, 1] - 1),
                     "std_fx_pct": 100 * result.std[c].get("fx", 0.0) / theirs[c].K[0, 0],
                     "centre_m": result.centre(c).tolist()} for c in range(len(names))],
                    "shared": {f"{names[i]}-{names[j]}": n for (i, j), n in sorted(result.shared.items())},
                    "squares": triangulated_squares(result, board), "notes": result.notes,
                    "disagreement": result.disagreement})
            rows.append(row)
            if not quiet:
                print(json.dumps(row, indent=1), flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m evaluate.calibration.rig_eval", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="*", default=[1, 2], help="drawn rigs to measure (0: validation)")
    parser.add_argument("--conditions", nargs="+", choices=CONDITIONS, default=list(CONDITIONS))
    parser.add_argument("--instants", type=int, default=60, help="instants (board poses) per drawn rig")
    parser.add_argument("--detectors", nargs="+", choices=DETECTORS, default=list(DETECTORS))
    parser.add_argument("--realdata", type=Path, default=None, help="folder holding caliscope_calibration/")
    parser.add_argument("--dark", type=int, default=0,
                        help="--realdata: also every frame darkened k = DARK (7: the paper's darkness, ~3 %% of the "
                             "light), each rig compared with the deep detector's lit one (put deep first in --detectors)")
    parser.add_argument("--rendered", type=Path, nargs="*", default=[],
                        help="folders of Blender-rendered rigs (python -m evaluate.calibration.rig_renders)")
    parser.add_argument("--rig-corners-alike", action="store_true",
                        help="the rig's bundle adjustment weighs every corner alike (as before 2026-11-26), each "
                             "camera's own calibration still by the corners' covariances")
    parser.add_argument("--out", type=Path, default=Path("report/rig_eval.json"))
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    if args.out.is_dir():  # checked before the work: the results are written only at the end
        parser.error(f"--out {args.out} is a folder: give the JSON file to write, e.g. {args.out / 'rig_eval.json'}")
    if args.realdata is not None and not (args.realdata / "caliscope_calibration").is_dir():
        parser.error(f"--realdata {args.realdata} holds no caliscope_calibration/ folder")
    weigh = not args.rig_corners_alike
    results = {"drawn": drawn_experiment(args.seeds, args.conditions, args.instants, args.detectors, args.quiet, weigh)}
    for folder in args.rendered:
        if not (folder / "truth.json").is_file():
            parser.error(f"--rendered {folder} holds no truth.json: render it with python -m evaluate.calibration.rig_renders")
        results.setdefault("rendered", []).extend(rendered_experiment(folder, args.detectors, args.quiet, weigh))
    if args.realdata is not None:
        results["caliscope"] = real_experiment(args.realdata, args.detectors, args.quiet, weigh, args.dark)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1))
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
