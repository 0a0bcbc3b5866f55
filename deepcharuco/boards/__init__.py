"""Boards: the `BoardSpec` (layout, dictionary, size, board files), its printable sheet, its printed face as the
detectors see it, and exact drawn views of it.

Imports only `deepcharuco.core`.
"""

from deepcharuco.boards.board import BoardSpec, BoardTexture
from deepcharuco.boards.dictionaries import dictionary_names, marker_family
from deepcharuco.boards.printing import Sheet, board_sheet
from deepcharuco.boards.synthetic import look_at_pose, render_board_view

__all__ = ["BoardSpec", "BoardTexture", "dictionary_names", "marker_family", "Sheet", "board_sheet",
           "look_at_pose", "render_board_view"]
