"""Random ChArUco boards of a marker family, for renders that teach a detector any board of it.

A *family* is a marker design whose OpenCV dictionaries are prefixes of one another:
``DICT_4X4_50``, ``_100`` and ``_250`` are the first 50, 100 and 250 markers of ``DICT_4X4_1000``
(checked by `check_prefixes`), so a board of any of them is a board of the family. Each rendered
frame draws its own board (`sample_board`) from an explicit generator: grid, marker/square
ratio, legacy layout, which dictionary of the family it names, the first marker ID, polarity
and mirroring. Plain numpy and OpenCV; no Blender.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.boards.dictionaries import MARKER_FAMILIES
from deepcharuco.core.errors import DeepCharucoError

# Family name -> its dictionaries, smallest first (each a prefix of the next): the runtime's table, which
# `Detector` picks a board's family model by.
FAMILIES = MARKER_FAMILIES


# Grids no training board of a family has, in either orientation: the report's unseen boards
# (`evaluate.paper.unseen_boards.UNSEEN_BOARDS`; a test checks they are all here), so that a family model
# is measured on boards its training never showed, whatever their marker size, IDs or polarity.
HELD_OUT_GRIDS: dict[str, tuple[tuple[int, int], ...]] = {
    "DICT_4X4": ((4, 5),),
    "DICT_5X5": ((8, 11),),
    "DICT_6X6": ((5, 7),),
}


def held_out(family: str, squares_x: int, squares_y: int) -> bool:
    """Whether a board of ``family`` with this grid (either orientation) is kept out of training renders."""
    return tuple(sorted((squares_x, squares_y))) in HELD_OUT_GRIDS.get(family, ())


class FamilyError(DeepCharucoError, ValueError):
    """An unknown marker family or impossible family sampling settings."""


def parse_families(text: str) -> tuple[str, ...]:
    """``"DICT_4X4"`` or ``"DICT_4X4,DICT_6X6"`` (case-insensitive; ``DICT_APRILTAG_36h11`` also names the
    AprilTag family) -> canonical names (upper case), in the given order, without repeats."""
    names: list[str] = []
    for part in text.split(","):
        name = part.strip().upper()
        name = {"DICT_APRILTAG_36H11": "APRILTAG_36H11"}.get(name, name)
        if name not in FAMILIES:
            raise FamilyError(f"unknown marker family {part.strip()!r}; use one of {', '.join(FAMILIES)} "
                              f"(several separated by commas)")
        if name not in names:
            names.append(name)
    if not names:
        raise FamilyError(f"--family is empty; use one of {', '.join(FAMILIES)}")
    return tuple(names)


def dictionary_size(name: str) -> int:
    return int(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)).bytesList.shape[0])


def check_prefixes(family: str) -> None:
    """Raise FamilyError unless each of the family's dictionaries is a prefix of the largest (same bits)."""
    dictionaries = FAMILIES[family]
    largest = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionaries[-1])).bytesList
    for name in dictionaries[:-1]:
        bits = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)).bytesList
        if not np.array_equal(bits, largest[: len(bits)]):
            raise FamilyError(f"{name} is not a prefix of {dictionaries[-1]} in this OpenCV build")


@dataclass(frozen=True)
class FamilySampling:
    """Ranges and probabilities of `sample_board` (defaults: issue 13's boards).

    ``id_span``: the first marker ID is drawn so the board's IDs stay below it (a board with more
    markers than that starts at 0 and uses what its dictionary has beyond). ``zero_first_p``: the
    probability of OpenCV's default first ID 0, which most printed boards have."""

    squares: tuple[int, int] = (3, 25)
    marker_ratio: tuple[float, float] = (0.5, 0.85)
    square_length_m: tuple[float, float] = (0.012, 0.06)
    legacy_p: float = 0.5
    inverted_p: float = 0.2
    mirrored_p: float = 0.05
    id_span: int = 250
    zero_first_p: float = 0.4

    def check(self) -> None:
        low, high = self.squares
        if not 3 <= low <= high:
            raise FamilyError(f"squares range must satisfy 3 <= low <= high, got {self.squares}")
        if not 0 < self.marker_ratio[0] <= self.marker_ratio[1] < 1:
            raise FamilyError(f"marker_ratio must lie in (0, 1), got {self.marker_ratio}")

    def to_dict(self) -> dict:
        return {"squares": list(self.squares), "marker_ratio": list(self.marker_ratio),
                "square_length_m": list(self.square_length_m), "legacy_p": self.legacy_p,
                "inverted_p": self.inverted_p, "mirrored_p": self.mirrored_p, "id_span": self.id_span,
                "zero_first_p": self.zero_first_p}


def sample_board(rng: np.random.Generator, families: tuple[str, ...], sampling: FamilySampling = FamilySampling()) -> BoardSpec:
    """One random board of one of ``families`` (chosen uniformly), drawn from ``rng``.

    Each side's square count is drawn log-uniformly in ``sampling.squares`` (a third of the boards have
    3-5 squares a side, a third 13-25, as printed boards are mostly small), then the grid is shrunk (the longer side
    first) until the family's largest dictionary holds its markers (only AprilTag 36h11, 587
    markers, ever needs it: 25x25 has 312). The dictionary named is a random one of the family
    that holds the board's IDs, as users print boards of any of them. A grid of `HELD_OUT_GRIDS` is
    drawn again: the report's unseen boards stay unseen."""
    family = families[int(rng.integers(len(families)))]
    dictionaries = FAMILIES[family]
    sizes = [dictionary_size(name) for name in dictionaries]
    low, high = sampling.squares
    while True:  # a held-out grid is drawn again (from the same generator: still a pure function of it)
        draws = np.exp(rng.uniform(math.log(low), math.log(high + 1), size=2))
        squares_x, squares_y = (min(int(v), high) for v in draws)
        while squares_x * squares_y // 2 > sizes[-1]:
            if squares_x >= squares_y:
                squares_x -= 1
            else:
                squares_y -= 1
        if not held_out(family, squares_x, squares_y):
            break
    markers = squares_x * squares_y // 2
    ratio = float(rng.uniform(*sampling.marker_ratio))
    square = float(math.exp(rng.uniform(*np.log(sampling.square_length_m))))
    legacy = bool(rng.random() < sampling.legacy_p)
    span = max(sampling.id_span, markers)
    first = 0 if rng.random() < sampling.zero_first_p else int(rng.integers(0, span - markers + 1))
    fitting = [name for name, size in zip(dictionaries, sizes) if size >= first + markers]
    dictionary = fitting[int(rng.integers(len(fitting)))]
    inverted = bool(rng.random() < sampling.inverted_p)
    mirrored = bool(rng.random() < sampling.mirrored_p)
    return BoardSpec(squares_x=squares_x, squares_y=squares_y, square_length=round(square, 6),
                     marker_length=round(square * ratio, 6), dictionary=dictionary, legacy=legacy,
                     inverted=inverted, mirrored=mirrored, first_marker_id=first)
