"""The ArUco dictionaries a board may use: their names as OpenCV spells them, their sizes, and the marker families
(4x4, 5x5, 6x6 ...) that the shipped family models cover (`marker_family`).
"""

from __future__ import annotations


import cv2

from deepcharuco.core.errors import BoardSpecError


def dictionary_names() -> list[str]:
    """The ArUco dictionary names OpenCV knows, e.g. ``DICT_5X5_50`` (upper case, sorted)."""
    return sorted({name.upper() for name in dir(cv2.aruco) if name.startswith("DICT_")})


def dictionary_id(name: str) -> int:
    for attr in dir(cv2.aruco):
        if attr.upper() == name.upper() and attr.startswith("DICT_"):
            return int(getattr(cv2.aruco, attr))
    raise BoardSpecError(
        f"unknown ArUco dictionary {name!r}; use one of: {', '.join(dictionary_names())}"
    )


# Marker family -> its OpenCV dictionaries, smallest first (each a prefix of the next: a board of any of them is a
# board of the family, `datagen.family.check_prefixes`). One family model reads them all.
MARKER_FAMILIES: dict[str, tuple[str, ...]] = {
    "DICT_4X4": ("DICT_4X4_50", "DICT_4X4_100", "DICT_4X4_250", "DICT_4X4_1000"),
    "DICT_5X5": ("DICT_5X5_50", "DICT_5X5_100", "DICT_5X5_250", "DICT_5X5_1000"),
    "DICT_6X6": ("DICT_6X6_50", "DICT_6X6_100", "DICT_6X6_250", "DICT_6X6_1000"),
    "DICT_7X7": ("DICT_7X7_50", "DICT_7X7_100", "DICT_7X7_250", "DICT_7X7_1000"),
    "APRILTAG_36H11": ("DICT_APRILTAG_36h11",),
}


def dictionary_size(name: str) -> int:
    """How many markers the OpenCV dictionary ``name`` holds."""
    return int(cv2.aruco.getPredefinedDictionary(dictionary_id(name)).bytesList.shape[0])


def more_markers_advice(dictionary: str, needed: int, otherwise: str = "fewer squares") -> str:
    """What to use when ``dictionary`` holds fewer than ``needed`` markers: the smallest larger dictionary of its
    family that holds them, else ``otherwise`` (never the same or a smaller dictionary)."""
    family = marker_family(dictionary)
    names = MARKER_FAMILIES.get(family, ()) if family else ()
    larger = [name for name in names if dictionary_size(name) >= needed]
    if larger:
        return f"use the larger dictionary {larger[0]} or {otherwise}"
    if names:
        return (f"no {family} dictionary holds {needed} (the largest, {names[-1]}, has {dictionary_size(names[-1])}): "
                f"use {otherwise}")
    return f"use {otherwise}"


def marker_family(dictionary: str) -> str | None:
    """The `MARKER_FAMILIES` family a dictionary belongs to (any case): ``DICT_4X4_250`` -> ``DICT_4X4``,
    ``DICT_APRILTAG_36h11`` -> ``APRILTAG_36H11``; None for the others (``DICT_ARUCO_ORIGINAL``, the smaller
    AprilTag sets)."""
    name = dictionary.upper()
    return next((family for family, names in MARKER_FAMILIES.items() if name in {n.upper() for n in names}), None)
