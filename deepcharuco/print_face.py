"""How a printed face is seen: inverted prints and mirror-printed back faces.

Both detectors look for a board in its canonical appearance (black squares and markers on
white, seen from the printed side, as OpenCV draws it). An inverted print (``inverted``) is
that image's negative, a board seen from a mirror-printed back face (``mirrored``) its
left-right mirror; `canonical_view` undoes both, `corners_from_canonical` maps corners found
there back to the image. Pixel convention: OpenCV's (centre of the top-left pixel at (0, 0)),
so a column x of an image W wide mirrors to W - 1 - x.
"""

from __future__ import annotations

import numpy as np

from deepcharuco.board import BoardSpec


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


def corners_from_canonical(corners: np.ndarray, board: BoardSpec, width: int) -> np.ndarray:
    """(N, 2) pixels found in `canonical_view`'s image -> (N, 2) pixels in the image itself."""
    if not board.mirrored:
        return corners
    mapped = np.array(corners, copy=True)
    mapped[:, 0] = (width - 1) - mapped[:, 0]
    return mapped
