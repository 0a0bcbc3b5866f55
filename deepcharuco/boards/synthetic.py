"""Exact synthetic views of a flat board through a pinhole camera (no renderer needed).

Used for tests, the bundled example and evaluation sanity checks: the board texture is
warped by the homography of a known pose, supersampled and box-filtered, so the true
corner positions are the projected board corners to well under 0.1 px.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec, BoardTexture
from deepcharuco.core.errors import OptionError


def texture_homography(texture: BoardTexture, K: np.ndarray, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """3x3 homography from texture pixels to image pixels for the pose (rvec, tvec)."""
    rotation, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))
    plane_to_image = np.asarray(K, np.float64) @ np.column_stack(
        [rotation[:, 0], rotation[:, 1], np.asarray(tvec, np.float64).ravel()]
    )
    return plane_to_image @ texture.texture_to_board_matrix()


def render_board_view(
    board: BoardSpec,
    K: np.ndarray,
    rvec: np.ndarray,
    tvec: np.ndarray,
    image_size: tuple[int, int] = (320, 240),
    *,
    margin: float | None = None,
    background: int = 90,
    supersample: int = 4,
    paint: Callable[[BoardTexture], np.ndarray] | None = None,
) -> np.ndarray:
    """A (H, W) uint8 image of the printed board under an undistorted pinhole camera.

    Args:
        board: the board; K: (3, 3) intrinsics; rvec, tvec: board -> camera pose.
        image_size: (width, height).
        margin: white paper around the grid in metres (default half a square).
        background: grey level outside the paper.
        supersample: the view is drawn at this many times the resolution and box-filtered
            down, which is what a sensor's pixel area does.
        paint: prints another image instead of the board's texture: called with the texture, returns
            a uint8 image of its size and map (look-alike boards: `paint_markers`).
    """
    width, height = image_size
    margin = 0.5 * board.square_length if margin is None else margin
    # Texture resolution ~ the supersampled image's at the nearest board point: enough detail,
    # and little minification (which bilinear warping would alias).
    rotation, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))
    corners = np.array([[0, 0, 0], [board.size_m[0], 0, 0], [0, board.size_m[1], 0], [*board.size_m, 0]])
    nearest_depth = max(float((corners @ rotation.T + np.ravel(tvec))[:, 2].min()), 1e-3)
    px_per_m = float(np.clip(supersample * K[0, 0] / nearest_depth, 200.0, 40000.0))
    px_per_m = min(px_per_m, 8000.0 / (max(board.size_m) + 2 * margin))
    texture = board.render_texture(px_per_m, margin)
    printed = texture.image if paint is None else paint(texture)
    half = (supersample - 1) / 2.0
    to_fine = np.array([[supersample, 0, half], [0, supersample, half], [0, 0, 1.0]])
    fine = cv2.warpPerspective(
        printed,
        to_fine @ texture_homography(texture, K, rvec, tvec),
        (width * supersample, height * supersample),
        flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=int(background),
    )
    return cv2.resize(fine, (width, height), interpolation=cv2.INTER_AREA)


def look_at_pose(
    board: BoardSpec, distance: float, tilt_x_deg: float = 0.0, tilt_y_deg: float = 0.0, roll_deg: float = 0.0,
    offset: tuple[float, float] = (0.0, 0.0),
) -> tuple[np.ndarray, np.ndarray]:
    """(rvec, tvec) of a board whose centre is ``distance`` m in front of the camera, tilted.

    The board is rotated about its own centre by ``roll`` (about Z), then ``tilt_y`` and
    ``tilt_x`` (degrees), and its centre shifted by ``offset`` metres in camera X/Y.
    """
    centre = np.array([board.size_m[0] / 2, board.size_m[1] / 2, 0.0])
    angles = np.radians([tilt_x_deg, tilt_y_deg, roll_deg])
    rx, _ = cv2.Rodrigues(np.array([angles[0], 0, 0]))
    ry, _ = cv2.Rodrigues(np.array([0, angles[1], 0]))
    rz, _ = cv2.Rodrigues(np.array([0, 0, angles[2]]))
    rotation = rx @ ry @ rz
    tvec = np.array([offset[0], offset[1], distance]) - rotation @ centre
    rvec, _ = cv2.Rodrigues(rotation)
    return rvec.ravel(), tvec


def paint_markers(texture: BoardTexture, marker_ids: np.ndarray | None) -> np.ndarray:
    """The texture's image with every marker replaced: by the markers ``marker_ids`` (M,) of the board's
    dictionary, in the board's marker order, or by white paper (None: a plain chessboard). The markers
    are drawn to the nearest texture pixel (not area-exact): for look-alike boards, not for labels."""
    board = texture.board
    image = texture.image.copy()
    paper, ink = (0, 255) if board.inverted else (255, 0)
    dictionary = board.cv_dictionary()
    _, corners = board.marker_corners()
    if board.mirrored:
        raise OptionError("paint_markers draws on the printed side: give the board unmirrored")
    for index, marker in enumerate(corners):
        (u0, v0), (u1, v1) = np.round(texture.board_to_texture(marker[[0, 2], :2])).astype(int)
        image[v0:v1 + 1, u0:u1 + 1] = paper
        if marker_ids is not None:
            side = int(u1 - u0 + 1)
            bits = cv2.aruco.generateImageMarker(dictionary, int(marker_ids[index]), side, borderBits=1)
            image[v0:v0 + side, u0:u0 + side] = np.where(bits > 127, paper, ink)[: image.shape[0] - v0, : image.shape[1] - u0]
    return image
