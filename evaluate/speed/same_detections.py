"""Every detector's detections of real captures, saved to compare two checkouts: a change that should only refuse
wrong boards (or only speed things up) must leave the right board's detections exactly as they were.

    python -m evaluate.speed.same_detections --realdata DIR --out before.npz [--step 10]    (in the old checkout)
    python -m evaluate.speed.same_detections --realdata DIR --out after.npz --compare before.npz

``DIR`` holds the real capture sets (opencv_tutorial/, calibtargets_22x22/: images; caliscope_calibration/cam_0.mp4,
cam_2.mp4, caliscope_extra/port_2.mp4: every ``--step``-th frame), each with its board.yaml. Prints per detector and
set the frames read, found and corners, and with ``--compare`` the (detector, frame) pairs whose IDs or corners differ,
and how far the corners of those with the same IDs moved.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from deepcharuco import BoardSpec
from deepcharuco.cli.detect import make_detector

IMAGE_SETS = ("opencv_tutorial", "calibtargets_22x22")
VIDEOS = ("caliscope_calibration/cam_0.mp4", "caliscope_calibration/cam_2.mp4", "caliscope_extra/port_2.mp4")


def capture_sets(root: Path, step: int) -> list[tuple[str, BoardSpec, list[tuple[str, np.ndarray]]]]:
    sets = []
    for folder in IMAGE_SETS:
        images = sorted(p for p in (root / folder).iterdir() if p.suffix.lower() in (".jpg", ".png"))
        sets.append((folder, BoardSpec.load(root / folder / "board.yaml"), [(p.name, cv2.imread(str(p))) for p in images]))
    for video in VIDEOS:
        capture, frames, index = cv2.VideoCapture(str(root / video)), [], 0
        while True:
            ok, frame = capture.read()
            if not ok:
                break
            if index % step == 0:
                frames.append((f"{video}:{index}", frame))
            index += 1
        sets.append((video, BoardSpec.load(root / video.split("/")[0] / "board.yaml"), frames))
    return sets


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m evaluate.speed.same_detections", description=__doc__.splitlines()[0])
    parser.add_argument("--realdata", required=True, type=Path)
    parser.add_argument("--out", required=True, type=Path)
    parser.add_argument("--step", type=int, default=10, help="every N-th frame of the videos")
    parser.add_argument("--compare", type=Path, help="an earlier --out to compare with")
    args = parser.parse_args(argv)
    result = {}
    sets = capture_sets(args.realdata, args.step)
    for name in ("opencv", "deep", "hybrid"):
        for label, board, frames in sets:
            detector = make_detector(name, board, "subpix" if name == "opencv" else "refinenet")
            found = corners = 0
            for frame_name, image in frames:
                detection = detector.detect(image)
                result[f"{name}|{label}|{frame_name}|ids"] = detection.ids
                result[f"{name}|{label}|{frame_name}|corners"] = detection.corners
                found += len(detection) > 0
                corners += len(detection)
            print(f"{name} {label}: {len(frames)} frames, {found} found, {corners} corners", flush=True)
    np.savez(args.out, **result)
    if args.compare is not None:
        before = np.load(args.compare)
        differ = sorted({key.rsplit("|", 1)[0] for key in set(before.files) | set(result)
                         if key not in before.files or key not in result or not np.array_equal(before[key], result[key])})
        print(f"{len(result) // 2} (detector, frame) pairs; {len(differ)} differ from {args.compare}"
              + "".join(f"\n  {key}" for key in differ))
        # A change that moves corners by rounding only (a refit, a faster arithmetic) keeps every ID: say by how much.
        same_ids = [key for key in differ if f"{key}|ids" in before.files and f"{key}|ids" in result
                    and np.array_equal(before[f"{key}|ids"], result[f"{key}|ids"])]
        moved = [float(np.abs(before[f"{key}|corners"] - result[f"{key}|corners"]).max()) for key in same_ids
                 if len(result[f"{key}|ids"])]
        print(f"of those, {len(differ) - len(same_ids)} with other IDs; {len(same_ids)} with the same IDs, their corners "
              f"moved by at most {max(moved, default=0.0):.2e} px")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
