"""The board read from its markers: corner candidates joined into chessboard cells (`lattice`), each cell read as a
marker (`marker_reader`, compiled in `decode_kernel` where numba is), the markers' vote for one view of the board
(`placement`), whether that view's markers are there and agree with the layout (`verification`), and its corners
settled against their neighbours (`settling`). Needs no training: any dictionary, size and layout reads the same way.
"""

# decode_kernel is left out: it needs numba (the `fast` extra), and the readers fall back without it.
__all__ = ["lattice", "marker_reader", "placement", "verification", "settling"]
