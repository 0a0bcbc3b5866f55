"""Overlays for a person to look at: detected corners, their IDs, the pose axes."""

from __future__ import annotations

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.core.detection import Detection
from deepcharuco.geometry.pose import Pose

CORNER_COLOUR = (0, 220, 0)  # BGR
TEXT_COLOUR = (0, 255, 255)


def draw_detection(
    image: np.ndarray,
    detection: Detection,
    pose: Pose | None = None,
    K: np.ndarray | None = None,
    dist: np.ndarray | None = None,
    board: BoardSpec | None = None,
) -> np.ndarray:
    """A BGR copy of ``image`` with corners, IDs and (given a pose and K) the board axes.

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
    if pose is not None and K is not None:
        board = board or BoardSpec()
        cv2.drawFrameAxes(canvas, K, dist if dist is not None else np.zeros(5), pose.rvec, pose.tvec,
                          board.square_length * 1.5, 2)
        label += f"  eps_re {pose.reprojection_error:.2f}px"
    cv2.putText(canvas, label, (5, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(canvas, label, (5, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return canvas
