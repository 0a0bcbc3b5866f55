"""Capture sets: folders of real photos and videos of one printed board, read lazily and checked.

    folder/
      board.yaml              the board (a BoardSpec file: README "Board files"; required)
      *.png, *.jpg, ...       photos, and/or
      *.mp4, *.avi, ...       videos, read one frame at a time (never whole)
      camera.yaml             intrinsics of every medium, or camera_<stem>.yaml for the medium <stem> (optional)
      labels.csv              per-frame truth, one corner a row: frame,id,x,y (optional)
      frames_review.csv       by-eye verdicts: frame,...,board_visible (yes | partial | edge-on | no) (optional)

Frames are named ``<photo file name>`` or ``<video file name>#<index>`` (index: the frame's number in the
video, from 0); labels.csv uses these names, frames_review.csv also ``<video stem>_f<index>`` (underscores
in the stem optional: ``cam0_f00012.png`` is frame 12 of ``cam_0.mp4``).
"""

from __future__ import annotations

import csv
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.cli.sources import IMAGE_SUFFIXES, SourceError, eight_bits
from deepcharuco.cli.video import VideoFrames
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.core.image import to_gray_u8
from deepcharuco.detection.board_hints import matching_variant
from deepcharuco.detection.opencv_detector import OpenCVDetector
from deepcharuco.geometry.camera import Camera, read_camera

VIDEO_SUFFIXES = {".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv"}
BOARD_FILE, LABELS_FILE, REVIEW_FILE = "board.yaml", "labels.csv", "frames_review.csv"
MIN_FOUND = 4  # OpenCV corners that show a board is in a frame (and fewest that give a pose)
BOARD_CHECK_FRAMES = 60  # sampled frames searched for the board before board.yaml is called wrong
VARIANT_FRAMES = 12  # frames the variants of a board that matches nothing are tried on


class CaptureError(DeepCharucoError):
    """A capture folder that cannot be evaluated: no board file, unreadable media, a board no frame shows."""


@dataclass(frozen=True)
class Medium:
    """One photo or video of a capture set; ``camera``: its intrinsics (None without a camera file)."""

    path: Path
    kind: str  # "image" | "video"
    camera: Camera | None = None


@dataclass
class CaptureFrame:
    """One frame: ``image`` (H, W) uint8 grayscale as the camera saw it (before any inversion), ``name``
    (module docstring), ``medium`` the photo or video it comes from, ``index`` its frame number (0 for a
    photo), ``camera`` its intrinsics scaled to the frame (or None), ``review`` the by-eye verdict or None."""

    image: np.ndarray
    name: str
    medium: Medium
    index: int
    camera: Camera | None = None
    review: str | None = None


@dataclass
class CaptureSet:
    """A capture folder, opened: the board, its media (photos first, then videos, each sorted by name),
    and the optional labels file and review verdicts. Frames are read by `frames` only."""

    folder: Path
    board: BoardSpec
    media: list[Medium]
    labels: Path | None = None
    review: dict[str, str] = field(default_factory=dict)  # frame name -> verdict
    problems: list[str] = field(default_factory=list)  # what `frames` could not read (damaged video stretches)

    @property
    def name(self) -> str:
        return self.folder.name

    @property
    def has_camera(self) -> bool:
        return any(m.camera is not None for m in self.media)

    def frames(self, step: int = 1, limit: int | None = None) -> Iterator[CaptureFrame]:
        """Every photo, and every ``step``-th frame of each video (0, step, 2 step, ...), at most ``limit`` a
        video; one frame in memory at a time. An image that cannot be decoded is a `CaptureError`; a video's
        damaged stretch is skipped and said (``problems``, stderr), and a video that ends early just ends."""
        if step < 1 or (limit is not None and limit < 1):
            raise ValueError(f"step and limit must be >= 1, got step={step}, limit={limit}")
        for medium in self.media:
            if medium.kind == "image":
                image = read_image(medium.path)
                yield self._frame(image, medium.path.name, medium, 0)
                continue
            for index, image in video_frames(medium.path, step, limit, self.problems):
                yield self._frame(image, f"{medium.path.name}#{index}", medium, index)

    def _frame(self, image: np.ndarray, name: str, medium: Medium, index: int) -> CaptureFrame:
        height, width = image.shape
        camera = None if medium.camera is None else _camera_for(medium, width, height)
        return CaptureFrame(image, name, medium, index, camera, self.review.get(name))


def open_capture_set(folder: str | Path, check_board: bool = True, step: int = 1, limit: int | None = None
                     ) -> CaptureSet:
    """Open a capture folder (module docstring) and check it: its board file, cameras and review file
    parse, every photo and video can be decoded, and (``check_board``) OpenCV finds at least 4 corners of
    the board in one of the first `BOARD_CHECK_FRAMES` frames ``frames(step, limit)`` yields. Raises
    `CaptureError` (or the board / camera file's own error) with the problem and the fix."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CaptureError(f"{folder} {'is not a folder' if folder.exists() else 'does not exist'}: give a folder "
                           f"holding {BOARD_FILE} and the photos or videos of that board")
    board_file = folder / BOARD_FILE
    if not board_file.is_file():
        raise CaptureError(f"{folder} has no {BOARD_FILE}: write the board there (squares_x, squares_y, square_length, "
                           f"marker_length, dictionary, legacy, inverted: README 'Board files')")
    board = BoardSpec.load(board_file)
    files = sorted(p for p in folder.iterdir() if p.is_file())
    images = [p for p in files if p.suffix.lower() in IMAGE_SUFFIXES]
    videos = [p for p in files if p.suffix.lower() in VIDEO_SUFFIXES]
    if not images and not videos:
        raise CaptureError(f"{folder} holds no photos ({', '.join(sorted(IMAGE_SUFFIXES))}) or videos "
                           f"({', '.join(sorted(VIDEO_SUFFIXES))}): add the captures of its board")
    shared = folder / "camera.yaml"
    media = []
    for path, kind in [(p, "image") for p in images] + [(p, "video") for p in videos]:
        own = folder / f"camera_{path.stem}.yaml"
        camera_file = own if own.is_file() else shared if shared.is_file() else None
        media.append(Medium(path, kind, None if camera_file is None else read_camera(camera_file)))
    for medium in media:  # refuse an unreadable file now, not after minutes of evaluation
        if medium.kind == "image":
            read_image(medium.path)
        else:
            if next(video_frames(medium.path, 1, 1), None) is None:
                _unreadable_video(medium.path, "OpenCV decodes no frame of it")
    labels = folder / LABELS_FILE
    captures = CaptureSet(folder, board, media, labels if labels.is_file() else None,
                          read_review(folder / REVIEW_FILE, media) if (folder / REVIEW_FILE).is_file() else {})
    if check_board:
        check_board_matches(captures, step, limit)
    return captures


def check_board_matches(captures: CaptureSet, step: int = 1, limit: int | None = None) -> int:
    """The number of the first sampled frame in which OpenCV finds >= 4 corners of ``captures.board``; a
    `CaptureError` when none of the first `BOARD_CHECK_FRAMES` do, naming the variant of board.yaml
    (polarity, legacy layout, squares swapped, mirrored) that OpenCV finds in them, if one does."""
    detector = OpenCVDetector(captures.board, refine="none")
    frames, number = [], -1
    for number, frame in enumerate(captures.frames(step, limit)):
        if len(detector.detect(frame.image)) >= MIN_FOUND:
            return number
        if len(frames) < VARIANT_FRAMES:
            frames.append(frame.image)
        if number + 1 >= BOARD_CHECK_FRAMES:
            break
    variant = matching_variant(frames, captures.board)
    where = f"{captures.folder / BOARD_FILE}"
    checked = f"none of the first {min(number + 1, BOARD_CHECK_FRAMES)} frames"
    if variant is not None:
        name, hits = variant
        raise CaptureError(f"OpenCV finds the board of {where} in {checked}, but with {name} it finds it in {hits} of "
                           f"the first {len(frames)}: set {name} in {where}")
    raise CaptureError(f"OpenCV finds the board of {where} in {checked}, nor with inverted, legacy, squares_x/"
                       f"squares_y swapped or mirrored changed: check its dictionary, squares and marker_length, and "
                       f"that the frames show the board")


def read_labels(path: Path, board: BoardSpec) -> dict[str, np.ndarray]:
    """labels.csv (header frame,id,x,y; one labelled corner a row, OpenCV pixels) -> frame name -> (C, 2)
    float32 corners by ID, NaN where the frame has no label."""
    labels: dict[str, np.ndarray] = {}
    with open(path, newline="") as handle:
        rows = csv.DictReader(handle)
        if not rows.fieldnames or not {"frame", "id", "x", "y"} <= set(rows.fieldnames):
            raise CaptureError(f"{path} must have the header frame,id,x,y (one labelled corner a row), got "
                               f"{rows.fieldnames}")
        for line, row in enumerate(rows, start=2):
            try:
                corner_id, x, y = int(row["id"]), float(row["x"]), float(row["y"])
            except (TypeError, ValueError):
                raise CaptureError(f"{path} line {line}: id must be an integer and x, y numbers, got {row}") from None
            if not 0 <= corner_id < board.num_corners:
                raise CaptureError(f"{path} line {line}: corner id {corner_id} is not on the board "
                                   f"(0..{board.num_corners - 1}): is board.yaml the labelled board?")
            corners = labels.setdefault(row["frame"], np.full((board.num_corners, 2), np.nan, np.float32))
            corners[corner_id] = (x, y)
    return labels


def read_review(path: Path, media: list[Medium]) -> dict[str, str]:
    """frames_review.csv -> frame name (module docstring) -> verdict (its ``board_visible`` column)."""
    videos = {_squash(m.path.stem): m.path.name for m in media if m.kind == "video"}
    verdicts = {}
    with open(path, newline="") as handle:
        rows = csv.DictReader(line for line in handle if not line.startswith("#"))
        if not rows.fieldnames or not {"frame", "board_visible"} <= set(rows.fieldnames):
            raise CaptureError(f"{path} must have the columns frame and board_visible, got {rows.fieldnames}")
        for row in rows:
            name = row["frame"]
            match = re.fullmatch(r"(.+)_f(\d+)(\.\w+)?", name)
            if match and _squash(match.group(1)) in videos:
                name = f"{videos[_squash(match.group(1))]}#{int(match.group(2))}"
            verdicts[name] = row["board_visible"].strip()
    return verdicts


def _squash(stem: str) -> str:
    return re.sub(r"[^0-9a-z]", "", stem.lower())


def _camera_for(medium: Medium, width: int, height: int) -> Camera:
    try:
        return medium.camera.for_image_size(width, height)
    except DeepCharucoError as error:
        raise CaptureError(f"{medium.path.name}: {error}") from None


def read_image(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise CaptureError(f"cannot read the photo {path}: not an image OpenCV can decode; re-save it as PNG or "
                           f"JPEG, or remove it from the folder")
    try:
        image = eight_bits(image, path.name)  # as `detect` reads the file: 16 bits by the range they use, never clipped
    except SourceError as error:
        raise CaptureError(f"{error}, or remove it from the folder") from None
    return to_gray_u8(image)


def _unreadable_video(path: Path, why: str):
    raise CaptureError(f"cannot read the video {path}: {why}; re-encode it (ffmpeg -i {path.name} -c:v libx264 "
                       f"{path.stem}_h264.mp4) or remove it from the folder")


def video_frames(path: Path, step: int, limit: int | None, problems: list[str] | None = None
                 ) -> Iterator[tuple[int, np.ndarray]]:
    """(frame number, (H, W) uint8) of every ``step``-th frame, at most ``limit``; frames in between are
    grabbed, not decoded into images, and one frame is held at a time. A damaged stretch is skipped
    (`deepcharuco.cli.video.VideoFrames`) and said in ``problems`` and on stderr."""
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        capture.release()
        _unreadable_video(path, "OpenCV cannot open it (unknown container or codec)")
    frames = VideoFrames(capture, step=step, limit=limit)
    for index, frame in frames:
        yield index, to_gray_u8(frame)
    if frames.skipped:
        line = frames.describe_skipped(path.name)
        print(f"warning: {line}", file=sys.stderr)
        if problems is not None:
            problems.append(line)


def absent_frames(captures: "CaptureSet", names) -> list[str]:
    """The ``names`` (module docstring: a photo's file name or ``<video file name>#<index>``) that are no frame of
    the set; a video's index is checked against its frame count where the container gives one (each video's
    count read once)."""
    media = {m.path.name: m for m in captures.media}
    counts: dict[str, int] = {}

    def exists(name: str) -> bool:
        if name in media:
            return media[name].kind == "image"
        video, _, index = name.rpartition("#")
        medium = media.get(video)
        if medium is None or medium.kind != "video" or not index.isdigit():
            return False
        if video not in counts:
            capture = cv2.VideoCapture(str(medium.path))
            counts[video] = int(capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
            capture.release()
        return counts[video] <= 0 or int(index) < counts[video]

    return [name for name in names if not exists(name)]
