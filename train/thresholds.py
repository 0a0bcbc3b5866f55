"""The score thresholds `train.bundle --threshold auto` chooses among, and how each is scored on a validation frame.

A threshold's balance is 2 x the right corners minus the corners reported (so right minus wrong: a wrong ID, > 3 px
off, or any corner on a frame without a board), summed over the frames; the largest balance wins, the higher
threshold among equals. Boards read by their markers are scored at lower thresholds too, down to LOW_THRESHOLDS
(a distilled network's confidences run low in the dark); their weak cells start at `placement.weak_confidence`
(`bundle._choose_threshold_markers` says why).
"""

from __future__ import annotations

import numpy as np

from deepcharuco.detection.metrics import match_corners

THRESHOLDS = tuple(np.round(np.arange(0.05, 0.951, 0.05), 2))
# A distilled student's point confidences run below its teacher's in the dark (2026-11-28: the paper's board's
# student at step 7,500 found 0.30-0.67 of the dark drawn corners at 0.1, 0.83-1.00 at 0.02, 0.98-1.00 at 0.01; the
# DICT_4X4 student at step 4,500, on caliscope's cam_0 darkened k = 7, 0 / 6 / 15 of 37 frames at 0.05 / 0.02 / 0.01,
# lite 15), so marker-read boards are also scored at these.
LOW_THRESHOLDS = (0.01, 0.02, 0.03, 0.04)
MARKER_THRESHOLDS = LOW_THRESHOLDS + tuple(float(t) for t in THRESHOLDS)


def tally_detections(balance: dict, detector, image: np.ndarray, corners: np.ndarray | None,
                     visible: np.ndarray | None) -> None:
    """Adds one frame to ``balance`` ({threshold: right - wrong}): ``detector.detect(image)`` at each of its thresholds
    against the frame's true ``corners`` (C, 2) and ``visible`` (C,), or None for a frame without a board."""
    for threshold in balance:
        detector.threshold = threshold
        detection = detector.detect(image)
        if corners is None:
            balance[threshold] -= len(detection.ids)
            continue
        balance[threshold] += 2 * match_corners(detection, corners, visible).num_correct - len(detection.ids)


def best_threshold(balance: dict) -> tuple[float, dict]:
    """(the threshold of the largest balance, the higher among equals; the balance as plain numbers)."""
    best = max(balance, key=lambda t: (balance[t], t))
    return float(best), {float(t): int(v) for t, v in balance.items()}
