"""Texture images as numpy arrays (no bpy): the target board, distractor boards, posters.

Every function returns (H, W) or (H, W, 3) uint8 with row 0 at the top (image convention);
`blender_scenes.objects` flips rows for Blender, whose image origin is the bottom left.
"""

from __future__ import annotations

import re
from functools import lru_cache

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec, BoardTexture

# Board textures are drawn area-exact at this density: ~5x the finest image sampling of a
# 0.2 m board filling a 320 px frame, so texture filtering never limits label accuracy.
BOARD_PX_PER_M = 6000.0


@lru_cache(maxsize=8)
def board_texture(board: BoardSpec, margin_m: float) -> BoardTexture:
    """The target board with ``margin_m`` of white paper around its grid."""
    margin_m = round(margin_m, 6)
    px_per_m = min(BOARD_PX_PER_M, 4096.0 / (max(board.size_m) + 2 * margin_m))
    return board.render_texture(px_per_m, margin_m)


@lru_cache(maxsize=32)
def distractor_texture(name: str) -> np.ndarray:
    """(H, W) uint8 image of a board that is *not* the target, from its name.

    Names: ``chessboard-CxR``, ``charuco-CxR-DICT[-idsN]`` (ChArUco with marker IDs starting at N),
    ``aruco-grid-CxR-DICT`` (an ArUco GridBoard). Each is printed with a white margin.
    """
    chess = re.fullmatch(r"chessboard-(\d+)x(\d+)", name)
    charuco = re.fullmatch(r"charuco-(\d+)x(\d+)-(DICT_\w+?)(?:-ids(\d+))?", name)
    grid = re.fullmatch(r"aruco-grid-(\d+)x(\d+)-(DICT_\w+)", name)
    square_px = 80
    if chess:
        cols, rows = int(chess[1]), int(chess[2])
        cells = (np.add.outer(np.arange(rows), np.arange(cols)) % 2).astype(np.uint8) * 255
        image = cv2.resize(cells, (cols * square_px, rows * square_px), interpolation=cv2.INTER_NEAREST)
    elif charuco:
        cols, rows, dictionary = int(charuco[1]), int(charuco[2]), charuco[3]
        first_id = int(charuco[4] or 0)
        cv_dict = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
        count = (cols * rows) // 2
        ids = np.arange(first_id, first_id + count, dtype=np.int32) % cv_dict.bytesList.shape[0]
        cv_board = cv2.aruco.CharucoBoard((cols, rows), 0.04, 0.03, cv_dict, ids)
        image = cv_board.generateImage((cols * square_px, rows * square_px))
    elif grid:
        cols, rows, dictionary = int(grid[1]), int(grid[2]), grid[3]
        cv_dict = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
        cv_board = cv2.aruco.GridBoard((cols, rows), 0.04, 0.01, cv_dict)
        image = cv_board.generateImage((cols * square_px, rows * square_px), marginSize=0)
    else:
        raise ValueError(f"unknown distractor {name!r}")
    margin = square_px // 2
    return cv2.copyMakeBorder(image, margin, margin, margin, margin, cv2.BORDER_CONSTANT, value=255)


@lru_cache(maxsize=16)
def poster_texture(name: str) -> np.ndarray:
    """(H, W, 3) uint8: one of scikit-image's bundled photographs (``skimage.data.<name>``)."""
    import skimage.data

    image = np.asarray(getattr(skimage.data, name)())
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    return np.ascontiguousarray(image[:, :, :3].astype(np.uint8))
