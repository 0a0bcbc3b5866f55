"""The paper's corner detection accuracy, shared by tests, training validation and evaluate."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from deepcharuco.core.detection import Detection

# The paper: a corner is correct when its ID is right and it lies within 3 px of the truth.
CORRECT_RADIUS_PX = 3.0


@dataclass(frozen=True)
class CornerMatch:
    """How one detection compares with the true corners of one image.

    Attributes:
        correct: (N,) bool, per detected corner (detection order): ID present in the truth
            and within ``radius`` px of it.
        errors: (N,) float64 distance in px to the true corner of the same ID (inf when that
            corner has no truth).
        accuracy: correct corners / number of board corners (the paper's metric, in [0, 1]).
    """

    correct: np.ndarray
    errors: np.ndarray
    accuracy: float

    @property
    def num_correct(self) -> int:
        return int(self.correct.sum())

    @property
    def subpixel_errors(self) -> np.ndarray:
        """Distances (px) of the correct corners only: the localisation error that counts."""
        return self.errors[self.correct]


def match_corners(
    detection: Detection,
    true_corners: np.ndarray,
    visible: np.ndarray | None = None,
    radius: float = CORRECT_RADIUS_PX,
) -> CornerMatch:
    """Score a detection against the truth with the paper's rule.

    Args:
        detection: detected IDs and corners.
        true_corners: (C, 2) true positions of all C board corners by ID; NaN rows have no truth.
        visible: optional (C,) bool; a detection of an invisible corner counts as wrong.
        radius: the correctness radius in pixels (3 in the paper).

    The accuracy divides by C, all board corners (16 on the paper's board), as the paper does.

    Example:
        >>> truth = np.array([[10.0, 10.0], [50.0, 10.0], [90.0, 10.0], [np.nan, np.nan]])
        >>> found = Detection(ids=np.array([0, 1, 3]), corners=np.array([[10.5, 10.0], [55.0, 10.0], [1.0, 1.0]]),
        ...                   scores=np.ones(3))
        >>> match = match_corners(found, truth)
        >>> match.correct, match.errors.round(2), match.accuracy
        (array([ True, False, False]), array([0.5, 5. , inf]), 0.25)
    """
    truth = np.asarray(true_corners, dtype=np.float64).reshape(-1, 2)
    num_corners = truth.shape[0]
    has_truth = np.all(np.isfinite(truth), axis=1)
    if visible is not None:
        has_truth &= np.asarray(visible, dtype=bool).reshape(-1)
    ids = detection.ids
    known = (ids >= 0) & (ids < num_corners)
    errors = np.full(len(detection), np.inf)
    usable = known.copy()
    usable[known] = has_truth[ids[known]]
    errors[usable] = np.linalg.norm(detection.corners[usable].astype(np.float64) - truth[ids[usable]], axis=1)
    correct = errors < radius
    return CornerMatch(correct=correct, errors=errors, accuracy=float(correct.sum()) / max(num_corners, 1))
