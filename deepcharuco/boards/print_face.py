"""How a printed face is seen: inverted prints and mirror-printed back faces.

Both detectors look for a board in its canonical appearance (black squares and markers on
white, seen from the printed side, as OpenCV draws it). An inverted print (``inverted``) is
that image's negative, a board seen from a mirror-printed back face (``mirrored``) its
left-right mirror; `canonical_view` undoes both, `corners_from_canonical` maps corners found
there back to the image. Pixel convention: OpenCV's (centre of the top-left pixel at (0, 0)),
so a column x of an image W wide mirrors to W - 1 - x.
"""

from __future__ import annotations

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec


def canonical_view(gray: np.ndarray, board: BoardSpec) -> np.ndarray:
    """(H, W) uint8 image -> the (H, W) uint8 image in which ``board`` looks as OpenCV draws it.

    An inverted print is negated about the image's brightest level (``max - gray``), so the
    exposure of the frame is kept."""
    if board.inverted:
        # Negate about the image's own white, not 255: a dark frame must stay dark (what the networks
        # learnt), not turn into a nearly white one.
        gray = int(gray.max()) - gray
    if board.mirrored:
        gray = gray[:, ::-1]
    return np.ascontiguousarray(gray)


# Local white (`canonical_view_local_white`): the negative is taken about the brightest print nearby, not the frame's,
# in windows of these fractions of the image's longer side (after a box blur against noise). Under a shadow, or on a
# small dark board in a frame whose white is a lamp, the negative about the frame's white turns the board into pale
# grey on white, which the point head never saw (a whole shadowed view of the report's inverted board; caliscope's dim
# board); about the local white it is a dimly lit board. The deep detector uses it for a board read by its markers
# when the frame's white finds nothing. Chosen on validation renders (4x6 DICT_4X4_250 inverted, seed 1515, 11 shadow
# and motion frames the frame's white loses: correct corners 21 -> 82 at these fractions; 37 at a window twice as
# wide, 60 with a third of the blur, 71 at half the window).
LOCAL_WHITE_WINDOW = 0.1
LOCAL_WHITE_BLUR = 0.028


def canonical_view_local_white(gray: np.ndarray, board: BoardSpec) -> np.ndarray:
    """`canonical_view` with an inverted print negated about its local white: each pixel's white is the brightest
    (box-blurred) level within `LOCAL_WHITE_WINDOW` of the longer side around it, smoothed over the same window (and
    never below the pixel itself). A print that is not inverted is unchanged."""
    if not board.inverted:
        return canonical_view(gray, board)
    longest = max(gray.shape)
    window = max(15, int(round(LOCAL_WHITE_WINDOW * longest)) | 1)
    blur = max(1, int(round(LOCAL_WHITE_BLUR * longest)) | 1)
    white = cv2.dilate(cv2.blur(gray, (blur, blur)), cv2.getStructuringElement(cv2.MORPH_RECT, (window, window)))
    white = np.maximum(cv2.blur(white, (window, window)), gray)
    negative = white - gray  # uint8: white >= gray
    if board.mirrored:
        negative = negative[:, ::-1]
    return np.ascontiguousarray(negative)


def corners_from_canonical(corners: np.ndarray, board: BoardSpec, width: int) -> np.ndarray:
    """(N, 2) pixels found in `canonical_view`'s image -> (N, 2) pixels in the image itself."""
    if not board.mirrored:
        return corners
    mapped = np.array(corners, copy=True)
    mapped[:, 0] = (width - 1) - mapped[:, 0]
    return mapped


def covariances_from_canonical(covariances: np.ndarray | None, board: BoardSpec) -> np.ndarray | None:
    """(N, 2, 2) corner covariances in `canonical_view`'s image -> the same in the image itself (a mirror flips
    the sign of the x-y term); None stays None."""
    if covariances is None or not board.mirrored:
        return covariances
    mapped = np.array(covariances, copy=True)
    mapped[:, 0, 1] *= -1
    mapped[:, 1, 0] *= -1
    return mapped
