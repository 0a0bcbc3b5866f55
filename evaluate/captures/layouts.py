"""Every detector on real captures searched with board files of other layouts than the print's, the same marker IDs:
transposed, and the IDs shifted by 1..3 (``first_marker_id`` + k). A right detector names no corner of a layout the
print contradicts; where the print's far edge is out of frame nothing tells the layouts apart.

    python -m evaluate.captures.layouts --realdata DIR [--frames 8]

``DIR`` holds the real capture sets (each folder with its board.yaml and images); prints, per set, detector and
layout, the corners found on each of the first ``--frames`` images.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import cv2

from deepcharuco import BoardSpec
from deepcharuco.cli.detect import make_detector

SETS = ("opencv_tutorial", "calibtargets_22x22")
SAMPLE = Path(__file__).resolve().parents[1] / "captures_sample" / "caliscope_cam1"


def layouts(board: BoardSpec, shifts: int = 3) -> dict[str, BoardSpec]:
    """The print's own layout ("right") and the others with its IDs: transposed, and shifted by 1..``shifts``."""
    found = {"right": board, "transposed": replace(board, squares_x=board.squares_y, squares_y=board.squares_x)}
    for k in range(1, shifts + 1):
        found[f"+{k}"] = replace(board, first_marker_id=board.first_marker_id + k)
    return found


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m evaluate.captures.layouts", description=__doc__.splitlines()[0])
    parser.add_argument("--realdata", required=True, type=Path, help="folder of the real capture sets")
    parser.add_argument("--frames", type=int, default=8, help="the first N images of each set")
    parser.add_argument("--detectors", nargs="+", default=["opencv", "deep", "hybrid"])
    args = parser.parse_args(argv)
    folders = [SAMPLE, *(args.realdata / name for name in SETS)]
    for folder in folders:
        board = BoardSpec.load(folder / "board.yaml")
        images = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".png"))[:args.frames]
        frames = [cv2.imread(str(p)) for p in images]
        for name in args.detectors:
            row = []
            for layout, spec in layouts(board).items():
                detector = make_detector(name, spec, "subpix" if name == "opencv" else "refinenet")
                row.append(f"{layout}: {[len(detector.detect(frame)) for frame in frames]}")
            print(f"{folder.name} {name}  " + "  ".join(row), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
