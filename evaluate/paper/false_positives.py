"""False positives: what the detectors report on boards that are not the target, and on photos without one.

A detector that answers with corners, and worse a pose, for a board that only looks like the
target is confidently wrong. Views of look-alike boards (each printed as the target board is,
same grid and marker/square ratio):

    other dictionary     the target's layout with the markers of another dictionary
    other marker IDs     the target's dictionary, the markers that follow the target's own IDs
    mirrored             the target printed mirrored (its back face through a mirror print)
    plain chessboard     the target's squares, no markers

are drawn exactly (`deepcharuco.boards.synthetic`, random poses from a seed, random exposure and sensor
noise), and scikit-image's bundled photos (posters, people, textures, a checkerboard) stand in
for frames with no board at all. Counted per detector: frames with any corner, frames with a pose.
"""

from __future__ import annotations

import cv2
import numpy as np
from tqdm import tqdm

from deepcharuco.boards.board import BoardSpec
from deepcharuco.boards.synthetic import look_at_pose, paint_markers, render_board_view
from deepcharuco.geometry.camera import Camera
from evaluate.paper.protocols import DetectorLike

OTHER_DICTIONARIES = ("DICT_4X4_250", "DICT_5X5_250", "DICT_6X6_250", "DICT_7X7_250", "DICT_APRILTAG_36h11")
MAX_PHOTO_CORNER_RATE = 0.02  # the target: at most 2 % of board-free photos with any corner reported
IMAGE_SIZE = (320, 240)


def look_alikes(target: BoardSpec) -> dict[str, tuple[BoardSpec, np.ndarray | None | str]]:
    """name -> (board to draw, what to paint): ``"own"`` = its own texture, None = no markers, (M,) marker IDs."""
    out: dict[str, tuple[BoardSpec, np.ndarray | None | str]] = {}
    plain = BoardSpec(**{**target.to_dict(), "mirrored": False})
    for dictionary in OTHER_DICTIONARIES:
        if dictionary.upper() == target.dictionary:
            continue
        try:
            other = BoardSpec(**{**target.to_dict(), "dictionary": dictionary})
        except ValueError:  # too few markers in that dictionary for this grid
            continue
        if _same_markers(other, target):
            continue  # DICT_5X5_250 starts with DICT_5X5_50's markers: the same board, not a look-alike
        out[f"other dictionary {dictionary}"] = (other, "own")
    size = target.cv_dictionary().bytesList.shape[0]
    if size >= 2 * target.num_markers:
        out["other marker IDs"] = (plain, np.arange(target.num_markers, 2 * target.num_markers))
    out["mirrored"] = (BoardSpec(**{**target.to_dict(), "mirrored": not target.mirrored}), "own")
    out["plain chessboard"] = (plain, None)
    return out


def _same_markers(board: BoardSpec, other: BoardSpec) -> bool:
    """True when both boards print the same bits in every marker square (a dictionary and its prefix)."""
    ids_a, ids_b = board.marker_corners()[0], other.marker_corners()[0]
    bits_a = board.cv_dictionary().bytesList[ids_a]
    bits_b = other.cv_dictionary().bytesList[ids_b]
    return bits_a.shape == bits_b.shape and np.array_equal(bits_a, bits_b)


def look_alike_views(target: BoardSpec, views: int, seed: int) -> dict[str, list[tuple[np.ndarray, np.ndarray]]]:
    """name -> ``views`` (image (240, 320) uint8, K (3, 3)) of each look-alike, poses and exposure from ``seed``."""
    camera = Camera.from_fov(*IMAGE_SIZE, hfov_deg=60.0)
    rng = np.random.default_rng(seed)
    out = {}
    for name, (board, paint) in look_alikes(target).items():
        images = []
        for _ in range(views):
            fill = rng.uniform(0.4, 0.9)
            distance = camera.K[0, 0] * max(board.size_m) / (fill * min(IMAGE_SIZE))
            rvec, tvec = look_at_pose(board, distance, rng.uniform(-35, 35), rng.uniform(-35, 35), rng.uniform(0, 360),
                                      offset=tuple(rng.uniform(-0.1, 0.1, 2) * distance))
            painter = None if isinstance(paint, str) else (lambda texture, ids=paint: paint_markers(texture, ids))
            image = render_board_view(board, camera.K, rvec, tvec, IMAGE_SIZE, background=int(rng.integers(30, 200)),
                                      paint=painter).astype(np.float64)
            image = image * rng.uniform(0.15, 1.0) + rng.normal(0.0, rng.uniform(0.5, 4.0), image.shape)
            images.append((np.clip(np.round(image), 0, 255).astype(np.uint8), camera.K))
        out[name] = images
    return out


def board_free_photos() -> list[tuple[str, np.ndarray]]:
    """(name, uint8 gray image) of scikit-image's bundled photos large enough to hold a board (>= 100 px)."""
    import skimage.data

    photos = []
    for name in sorted(skimage.data.__all__):
        loader = getattr(skimage.data, name)
        if not callable(loader) or name in ("download_all", "lbp_frontal_face_cascade_filename", "data_dir"):
            continue
        try:
            image = loader()
        except (KeyboardInterrupt, SystemExit):
            raise
        except BaseException:  # noqa: BLE001 - not bundled, needs a download (under pytest it raises a skip)
            continue
        if not isinstance(image, np.ndarray) or image.ndim not in (2, 3) or min(image.shape[:2]) < 100:
            continue
        if image.ndim == 3 and image.shape[2] not in (3, 4):
            continue  # volumes, not photos
        if image.dtype != np.uint8:  # binary masks and float phantoms: stretched to 0..255
            values = image.astype(np.float64)
            image = np.round(255 * (values - values.min()) / max(float(np.ptp(values)), 1e-9)).astype(np.uint8)
        if image.ndim == 3:
            image = cv2.cvtColor(image[:, :, :3], cv2.COLOR_RGB2GRAY)
        photos.append((name, image))
    return photos


def false_positive_experiment(detectors: dict[str, DetectorLike], target: BoardSpec, views: int = 10, seed: int = 0,
                              quiet: bool = False) -> dict:
    """Frames with corners and with a pose, per detector, on look-alikes of ``target`` and board-free photos."""
    sets = look_alike_views(target, views, seed)
    photos = board_free_photos()
    sets["board-free photos"] = [(image, Camera.from_fov(image.shape[1], image.shape[0]).K) for _, image in photos]
    rows = []
    total = len(detectors) * sum(len(items) for items in sets.values())
    with tqdm(total=total, desc="false positives", unit="image", disable=quiet) as bar:
        for name, items in sets.items():
            row = {"set": name, "frames": len(items)}
            for detector_name, detector in detectors.items():
                with_corners = with_pose = 0
                for image, K in items:
                    detection = detector.detect(image)
                    with_corners += len(detection.ids) > 0
                    with_pose += detector.estimate_pose(detection, K) is not None
                    bar.update(1)
                row[detector_name] = {"with_corners": with_corners, "with_pose": with_pose}
            rows.append(row)
    return {"target": target.to_dict(), "views_per_look_alike": views, "seed": seed,
            "photos": [name for name, _ in photos], "table": rows}


def targets(result: dict, detector: str = "deep") -> list[tuple[str, float, str, bool]]:
    """(what, value, goal, met): no pose on any look-alike or photo; <= 2 % of photos with any corner."""
    table = result.get("table", [])
    if not table or detector not in table[0]:
        return []
    poses = sum(row[detector]["with_pose"] for row in table)
    photos = next((row for row in table if row["set"] == "board-free photos"), None)
    out = [("poses on look-alike boards and board-free photos", poses, "0", poses == 0)]
    if photos and photos["frames"]:
        rate = photos[detector]["with_corners"] / photos["frames"]
        out.append(("board-free photos with any corner reported", rate, f"<= {MAX_PHOTO_CORNER_RATE:.2f}",
                    rate <= MAX_PHOTO_CORNER_RATE))
    return out


def sections(result: dict, labels: dict) -> list[tuple[str, str, list[list[str]], list[str]]]:
    """The report's false-positive section: frames with corners / with a pose, per set and detector."""
    table = result.get("table", [])
    if not table:
        return []
    names = [key for key in table[0] if key not in ("set", "frames")]
    rows = [["set", "frames"] + [f"{labels.get(n, n)}: corners / pose" for n in names]]
    for row in table:
        rows.append([row["set"], str(row["frames"])] + [f"{row[n]['with_corners']} / {row[n]['with_pose']}" for n in names])
    text = (f"Frames in which each detector reports any corner / a pose. Look-alike boards ({result['views_per_look_alike']} "
            "exact views each, random pose, exposure and sensor noise) share the target's grid and marker/square ratio; "
            f"board-free photos are scikit-image's {len(result['photos'])} bundled images. Targets: no pose at all, and at "
            f"most {100 * MAX_PHOTO_CORNER_RATE:.0f} % of the photos with any corner.")
    return [("False positives: look-alike boards and photos without a board", text, rows, [])]
