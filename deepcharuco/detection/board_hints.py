"""When no frame shows the board: what the frames do show, so that a run that finds nothing says what to fix.

The mistakes people make describing a board (`board_variants`: polarity, legacy layout, squares_x and
squares_y swapped, a mirrored face) are tried with OpenCV on a few of the frames; failing those, the
frames are searched for markers of every marker family (printed or inverted), which names the dictionary
the board file should have. One line, `what_matches`, for the commands to print.
"""

from __future__ import annotations

import itertools
from dataclasses import replace
from typing import Iterator

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.boards.dictionaries import MARKER_FAMILIES, dictionary_size, marker_family
from deepcharuco.core.image import to_gray_u8
from deepcharuco.detection.opencv_detector import OpenCVDetector

MIN_FOUND = 4  # corners (or markers) that show a board is in a frame, and the fewest that give a pose
# One dictionary per marker family, the largest (its IDs include every smaller one's), and the others OpenCV knows.
SEARCHED_DICTIONARIES = ("DICT_4X4_1000", "DICT_5X5_1000", "DICT_6X6_1000", "DICT_7X7_1000", "DICT_ARUCO_ORIGINAL",
                         "DICT_APRILTAG_36h11")


def board_variants(board: BoardSpec) -> Iterator[tuple[str, BoardSpec]]:
    """(the change, as a board file would spell it; the board) for the mistakes people make writing a board
    file: the polarity, the legacy layout, squares_x and squares_y swapped, each alone and in pairs, and a
    mirrored face."""
    single = [(f"inverted: {_yaml(not board.inverted)}", {"inverted": not board.inverted}),
              (f"legacy: {_yaml(not board.legacy)}", {"legacy": not board.legacy})]
    if board.squares_x != board.squares_y:
        single.append((f"squares_x: {board.squares_y}, squares_y: {board.squares_x}",
                       {"squares_x": board.squares_y, "squares_y": board.squares_x}))
    changes = single + [(f"{a} and {b}", {**change_a, **change_b})
                        for (a, change_a), (b, change_b) in itertools.combinations(single, 2)]
    changes.append((f"mirrored: {_yaml(not board.mirrored)}", {"mirrored": not board.mirrored}))
    for name, change in changes:
        yield name, replace(board, **change)


def _yaml(flag: bool) -> str:
    return "true" if flag else "false"


def matching_variant(frames: list[np.ndarray], board: BoardSpec) -> tuple[str, int] | None:
    """(the change of `board_variants` with which OpenCV finds >= `MIN_FOUND` corners in the most of ``frames``,
    in how many), or None when no variant is found in any."""
    found = [(name, hits) for name, variant in board_variants(board)
             if (hits := sum(len(OpenCVDetector(variant, refine="none").detect(f)) >= MIN_FOUND for f in frames))]
    return max(found, key=lambda item: item[1]) if found else None


def markers_seen(frames: list[np.ndarray]) -> tuple[str, bool, int, list[int]] | None:
    """(dictionary, inverted print, frames with >= `MIN_FOUND` of its markers, the IDs seen) of the dictionary in
    `SEARCHED_DICTIONARIES` whose markers most frames show, or None when no frame shows a dictionary's markers."""
    grays = [to_gray_u8(frame) for frame in frames]
    views = {False: grays, True: [255 - gray for gray in grays]}  # as printed, and a white-on-black print's negative
    best = None
    for name in SEARCHED_DICTIONARIES:
        detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)))
        for inverted, images in views.items():
            hits, ids_seen = 0, set()
            for image in images:
                _, ids, _ = detector.detectMarkers(image)
                if ids is not None and len(ids) >= MIN_FOUND:
                    hits += 1
                    ids_seen.update(int(i) for i in ids.ravel())
            if hits and (best is None or hits > best[2]):
                best = (name, inverted, hits, sorted(ids_seen))
    return best


def what_matches(frames: list[np.ndarray], board: BoardSpec, board_file: str | None) -> str:
    """One line for a run that found the board in none of its frames: the board file's change that makes OpenCV
    find it in ``frames`` (a sample of the run's frames), else the dictionary whose markers they show, else what
    to check. ``board_file``: the file the board came from, None when none was given (the default was assumed)."""
    where = board_file or "a board file (--board board.yaml)"
    looked = f"{len(frames)} frame(s) looked at"
    variant = matching_variant(frames, board)
    if variant is not None:
        change, hits = variant
        return f"with {change} OpenCV finds the board in {hits} of {looked}: set {change} in {where}"
    seen = markers_seen(frames)
    assumed = "" if board_file else (f"no --board was given, so the {board.squares_x}x{board.squares_y} "
                                     f"{board.dictionary} board was assumed; ")
    if seen is not None:
        name, inverted, hits, ids = seen
        family = marker_family(name)
        smallest = next((d for d in MARKER_FAMILIES.get(family, ()) if dictionary_size(d) > ids[-1]), name)
        return (f"{assumed}{family or name} markers{' printed inverted (white on black)' if inverted else ''} are in "
                f"{hits} of {looked} (IDs {ids[0]}..{ids[-1]}): describe that board in {where} (dictionary: "
                f"{smallest}{' or larger' if smallest != name else ''}{', inverted: true' if inverted else ''}; "
                f"its squares_x and squares_y)")
    return (f"{assumed}no markers of any dictionary OpenCV knows are in the {looked}: check that the frames show "
            f"the board in focus and light")
