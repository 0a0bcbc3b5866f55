"""Regenerate the bundled example: ``python -m deepcharuco.examples.make_examples``.

A synthetic 320x240 view of the paper's board under a webcam-like camera with uneven light
and sensor noise (seed 0), plus that camera's intrinsics file. Deterministic.
"""

from pathlib import Path

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.boards.synthetic import look_at_pose, render_board_view
from deepcharuco.geometry.camera import Camera, write_camera

HERE = Path(__file__).parent


def make_example(seed: int = 0) -> tuple[np.ndarray, Camera]:
    rng = np.random.default_rng(seed)
    board = BoardSpec()
    camera = Camera.from_fov(320, 240, hfov_deg=60.0)
    rvec, tvec = look_at_pose(board, 0.38, tilt_x_deg=25.0, tilt_y_deg=-20.0, roll_deg=12.0, offset=(0.02, -0.01))
    view = render_board_view(board, camera.K, rvec, tvec, camera.image_size, background=70).astype(np.float64)
    ys, xs = np.mgrid[0:240, 0:320]
    light = 0.55 + 0.4 * np.exp(-((xs - 90) ** 2 + (ys - 60) ** 2) / (2 * 140.0**2))
    noisy = view * light + rng.normal(0.0, 3.0, view.shape)
    return np.clip(np.round(noisy), 0, 255).astype(np.uint8), camera


if __name__ == "__main__":
    image, camera = make_example()
    cv2.imwrite(str(HERE / "board_320x240.png"), image)
    write_camera(HERE / "webcam_320x240.yaml", camera)
    print(f"wrote {HERE / 'board_320x240.png'} and {HERE / 'webcam_320x240.yaml'}")
