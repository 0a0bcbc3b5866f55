"""The README's picture: OpenCV and the deep detector on the same dark view of a board.

    python -m evaluate.paper.readme_figure --out docs/dark_frame.jpg

A 7x5 DICT_6X6_250 board (a board the networks never trained on, found by its markers with the shipped
DICT_6X6 family model) drawn at 640x480 through an undistorted 60-degree camera, darkened as the paper's
protocol does at k = 8 (`evaluate.paper.protocols.darken`: ~2 % of the light) with sensor noise, then each detector's
corners and pose drawn on a brightened copy (the image itself is nearly black). Deterministic: seed 0.
"""

from __future__ import annotations

import argparse
import sys

import cv2
import numpy as np

from deepcharuco import BoardSpec, Camera, Detector, OpenCVDetector
from deepcharuco.boards.synthetic import look_at_pose, render_board_view
from deepcharuco.cli.common import run_command
from deepcharuco.cli.draw import draw_detection
from deepcharuco.core.files import write_atomic
from evaluate.paper.protocols import darken

BOARD = BoardSpec(7, 5, 0.03, 0.022, "DICT_6X6_250")
DARKNESS_K = 8


def dark_view(seed: int = 0) -> tuple[np.ndarray, Camera]:
    camera = Camera.from_fov(640, 480, 60.0)
    rvec, tvec = look_at_pose(BOARD, 0.45, tilt_x_deg=25.0, tilt_y_deg=-20.0, roll_deg=8.0)
    image = render_board_view(BOARD, camera.K, rvec, tvec, camera.image_size, supersample=2)
    dark = darken(image, DARKNESS_K).astype(np.float32)
    noise = np.random.default_rng(seed).normal(0.0, 0.8, dark.shape)
    return np.clip(np.rint(dark + noise), 0, 255).astype(np.uint8), camera


def figure(seed: int = 0) -> tuple[np.ndarray, dict[str, int]]:
    """(the side-by-side picture, corners each detector found)."""
    image, camera = dark_view(seed)
    shown = cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX)  # to see anything; the detectors got `image`
    panels, found = [], {}
    for name, detector in (("OpenCV + cornerSubPix", OpenCVDetector(BOARD)), ("Deep ChArUco", Detector(board=BOARD))):
        detection = detector.detect(image)
        pose = detector.estimate_pose(detection, camera.K, camera.dist) if len(detection) >= 4 else None
        panel = draw_detection(shown, detection, pose, camera, BOARD)
        label = f"{name}: {len(detection)} of {BOARD.num_corners} corners" + ("" if pose else ", no pose")
        cv2.putText(panel, label, (12, 50), cv2.FONT_HERSHEY_SIMPLEX, 0.75, (0, 255, 255), 2, cv2.LINE_AA)
        cv2.putText(panel, f"darkness k = {DARKNESS_K} (~2 % of the light), shown brightened", (12, 465),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 1, cv2.LINE_AA)
        panels.append(panel)
        found[name] = len(detection)
    return np.hstack(panels), found


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m evaluate.paper.readme_figure", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="docs/dark_frame.jpg", help="the picture (JPEG)")
    parser.add_argument("--seed", type=int, default=0, help="the sensor noise's seed")
    args = parser.parse_args(argv)

    def body() -> None:
        picture, found = figure(args.seed)
        write_atomic(args.out, cv2.imencode(".jpg", picture, [cv2.IMWRITE_JPEG_QUALITY, 85])[1].tobytes())
        print(f"{args.out}: " + ", ".join(f"{name} {n} corners" for name, n in found.items()))

    return run_command(body)


if __name__ == "__main__":
    sys.exit(main())
