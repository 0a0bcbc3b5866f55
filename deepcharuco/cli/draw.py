"""Overlays for a person to look at: detected corners, their IDs, the pose axes."""

from __future__ import annotations

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.core.detection import Detection
from deepcharuco.geometry.camera import Camera
from deepcharuco.geometry.pose import Pose

CORNER_COLOUR = (0, 220, 0)  # BGR
TEXT_COLOUR = (0, 255, 255)
AXIS_COLOURS = ((0, 0, 255), (0, 255, 0), (255, 0, 0))  # x, y, z: red, green, blue (BGR), as cv2.drawFrameAxes


def draw_detection(
    image: np.ndarray,
    detection: Detection,
    pose: Pose | None = None,
    camera: Camera | None = None,
    board: BoardSpec | None = None,
) -> np.ndarray:
    """A BGR copy of ``image`` with corners, IDs and (given a pose and the ``camera`` it was found with) the board's
    axes, projected through the camera's own model (a fisheye's too: ``cv2.drawFrameAxes`` would read its k1..k4 as
    k1 k2 p1 p2).

    Corner markers are drawn at sub-pixel precision (cv2 shift=4) so a viewer can judge them.
    """
    canvas = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    scale = 16  # 4 fractional bits
    for corner_id, (x, y) in zip(detection.ids, detection.corners):
        centre = (int(round(x * scale)), int(round(y * scale)))
        cv2.circle(canvas, centre, 3 * scale, CORNER_COLOUR, 1, cv2.LINE_AA, shift=4)
        cv2.putText(canvas, str(corner_id), (int(x) + 4, int(y) - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35,
                    TEXT_COLOUR, 1, cv2.LINE_AA)
    label = f"{len(detection)} corners"
    if pose is not None and camera is not None:
        length = 1.5 * (board or BoardSpec()).square_length
        ends = camera.project(np.array([[0, 0, 0], [length, 0, 0], [0, length, 0], [0, 0, length]], np.float64),
                              pose.rvec, pose.tvec)
        if np.isfinite(ends).all():
            origin = (int(round(ends[0, 0] * scale)), int(round(ends[0, 1] * scale)))
            for end, colour in zip(ends[1:], AXIS_COLOURS):
                cv2.line(canvas, origin, (int(round(end[0] * scale)), int(round(end[1] * scale))), colour, 2,
                         cv2.LINE_AA, shift=4)
        label += f"  eps_re {pose.reprojection_error:.2f}px"
    cv2.putText(canvas, label, (5, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(canvas, label, (5, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return canvas
