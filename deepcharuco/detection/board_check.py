"""Board-geometry check of a detection: its IDs must agree with one view of the board's plane.

ChArUcoNet's point head learns *where* corners are long before its ID head learns *which*
corner each one is: under blur, darkness or a short training run the ID softmax is flat, its
argmax often still right, and one wrong ID is enough for PnP to return a confidently wrong
pose. The board is a plane, so every correct (ID, pixel) pair obeys one homography from the
board's (x, y) to the image (lens distortion aside; the tolerance absorbs a little):

1. ``id_hypotheses``: each confident cell proposes its most likely IDs (2 by default),
   however unsure the ID head is about them;
2. ``fit_board_homography``: RANSAC over the proposals; a consensus of at least
   ``MIN_CONSENSUS`` pairs, spread over the board, whose homography does not mirror the board
   (its printed face is never seen mirrored) is a verified view;
3. ``assign_ids``: every corner the view predicts takes the confident cell found within a few
   pixels of it. Wrong IDs are dropped and corners whose ID the network missed are kept.

All positions are OpenCV pixels (centre of the top-left pixel at (0, 0)).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from deepcharuco.core.detection import no_corners
from deepcharuco.core.vectors import homogeneous, pairwise_distances
from deepcharuco.geometry.pose import MIN_SPREAD_RATIO
from deepcharuco.networks.cells import CellCandidates

GEOMETRY_MODES = ("repair", "filter", "none")
# A homography has 8 degrees of freedom: 4 pairs fit any 4 points exactly. One more pair is one check,
# and on the sequences a 5th wrong ID still fitted a warped homography (and a twisted pose) now and then;
# two checks did not.
MIN_CONSENSUS = 6
TOLERANCE_PX = 3.0  # the protocols' own "right corner" distance
# IDs each cell proposes to RANSAC: the second most likely ID is right often enough under blur and darkness
# to matter; more proposals add outliers faster than inliers.
HYPOTHESES_PER_CELL = 2
RANSAC_ITERATIONS = 1000
# A predicted corner claims a candidate no farther than this fraction of its distance to the nearest other corner.
MAX_SPACING_FRACTION = 0.4


@dataclass(frozen=True)
class BoardView:
    """A verified board view. ``homography``: (3, 3) board (x, y) metres -> image pixels, scaled so that
    board points in view have w > 0. ``inliers``: (M,) bool over the pairs it was fit to."""

    homography: np.ndarray
    inliers: np.ndarray


def apply_homography(homography: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(P, 2) board points -> (P, 2) image points and their (P,) homogeneous w."""
    mapped = homogeneous(xy) @ homography.T
    return mapped[:, :2] / mapped[:, 2:], mapped[:, 2]


def id_hypotheses(candidates: CellCandidates, per_cell: int = HYPOTHESES_PER_CELL,
                  min_prob: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Each candidate cell with each of its ``per_cell`` most likely IDs -> (ids (P,), pixels (P, 2)), cell by
    cell; an ID after the first only where the ID head gives it at least ``min_prob``."""
    per_cell = min(per_cell, candidates.id_prob.shape[1])
    top = np.argsort(-candidates.id_prob, axis=1, kind="stable")[:, :per_cell]
    keep = np.take_along_axis(candidates.id_prob, top, axis=1) >= min_prob
    keep[:, 0] = True
    return top[keep].astype(np.int64), np.repeat(candidates.pixels, keep.sum(axis=1), axis=0)


def fit_board_homography(board_xy: np.ndarray, pixels: np.ndarray, tolerance_px: float = TOLERANCE_PX,
                         min_consensus: int = MIN_CONSENSUS) -> BoardView | None:
    """RANSAC homography from ``board_xy`` (M, 2) metres to ``pixels`` (M, 2); None unless a consensus of
    ``min_consensus`` pairs, not (nearly) on one line of the board, agrees within ``tolerance_px`` and the
    mapping keeps the board's handedness."""
    if len(board_xy) < max(4, min_consensus):
        return None
    src, dst = np.asarray(board_xy, np.float64), np.asarray(pixels, np.float64)
    # OpenCV's RANSAC seeds its own generator on each call: the same pairs give the same answer.
    homography, mask = cv2.findHomography(src, dst, cv2.RANSAC, tolerance_px,
                                            maxIters=RANSAC_ITERATIONS, confidence=0.999)
    if homography is None or mask is None or int(mask.sum()) < min_consensus:
        return None
    inliers = mask.ravel().astype(bool)
    # Pairs along one board line pin the homography down in one direction only: any wrong ID fits then.
    spread = np.linalg.svd(src[inliers] - src[inliers].mean(0), compute_uv=False)
    if spread[1] < MIN_SPREAD_RATIO * spread[0]:
        return None
    _, w = apply_homography(homography, src[inliers])
    if np.any(w * w[0] <= 0):  # the board's line at infinity runs between the inliers: not a camera view
        return None
    homography = homography * np.sign(w[0])
    # Board x right and y down, seen from its printed side, stay right-handed in the image (y down too);
    # a mirrored consensus is a wrong set of IDs that happens to be self-consistent.
    if np.linalg.det(homography) <= 0:
        return None
    return BoardView(homography=homography, inliers=inliers)


def in_image(homography: np.ndarray, board_xy: np.ndarray, image_size: tuple[int, int]
             ) -> tuple[np.ndarray, np.ndarray]:
    """(P, 2) board points -> (their (P, 2) pixels under ``homography``, (P,) bool: in front of the camera and inside
    an image of ``image_size`` (width, height), pixel centres from 0)."""
    predicted, w = apply_homography(homography, np.asarray(board_xy, np.float64))
    width, height = image_size
    inside = (w > 0) & (predicted[:, 0] > -0.5) & (predicted[:, 1] > -0.5) \
        & (predicted[:, 0] < width - 0.5) & (predicted[:, 1] < height - 0.5)
    return predicted, inside


def assign_ids(view: BoardView, board_xy: np.ndarray, candidates: CellCandidates, image_size: tuple[int, int],
               tolerance_px: float = TOLERANCE_PX) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Corners of a verified view matched to candidates: mutual nearest pairs no farther apart than
    ``tolerance_px`` (and than a fraction of the predicted corner spacing).

    Args:
        view: the verified view; board_xy: (N, 2) every board corner, in ID order.
        candidates: ChArUcoNet's confident cells; image_size: (width, height).

    Returns:
        (ids (K,), pixels (K, 2) float32, scores (K,) float32), strongest first. A corner's score is
        its cell's point confidence: its ID comes from the board's geometry, not the ID head.
    """
    predicted, in_view = in_image(view.homography, board_xy, image_size)
    if len(candidates) == 0 or not in_view.any():
        return no_corners()
    spacing = pairwise_distances(predicted, predicted)
    np.fill_diagonal(spacing, np.inf)
    reach = np.minimum(tolerance_px, MAX_SPACING_FRACTION * spacing.min(axis=1))
    distance = pairwise_distances(predicted, candidates.pixels.astype(np.float64))  # (N, M)
    distance[~in_view] = np.inf
    nearest_candidate = distance.argmin(axis=1)
    nearest_corner = distance.argmin(axis=0)
    corner = np.arange(len(predicted))
    ids = np.flatnonzero((nearest_corner[nearest_candidate] == corner)
                         & (distance[corner, nearest_candidate] <= reach)).astype(np.int64)
    if len(ids) == 0:
        return no_corners()
    cells = nearest_candidate[ids]
    scores = candidates.confidence[cells]
    order = np.argsort(-scores, kind="stable")
    return ids[order], candidates.pixels[cells][order], scores[order].astype(np.float32)
