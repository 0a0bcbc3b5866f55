"""What `deepcharuco detect` (and `calibrate`) read: an image, a folder of images, a video or a camera, opened as
one `Source` of frames with their numbers in the recording (`frame_numbers`: what a rig pairs by); a folder's
unreadable image is skipped and named, and the command's own overlays are never read back as input.
"""

from __future__ import annotations

import sys
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from deepcharuco.cli.video import VideoFrames
from deepcharuco.core.errors import DeepCharucoError


IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm"}


class SourceError(DeepCharucoError):
    """An input the CLI cannot open."""


@dataclass
class Source:
    """Frames to process: ``frames`` yields (name, BGR or gray image); ``skipped`` collects the
    "name: reason" of a folder's images that could not be read (as ``frames`` meets them)."""

    stem: str
    kind: str  # "image" | "images" | "video" | "camera"
    frames: Iterator[tuple[str, np.ndarray]]
    fps: float
    total: int | None
    skipped: list[str] = field(default_factory=list)
    overlay_names: dict[str, str] = field(default_factory=dict)  # folder: image file name -> overlay file name
    video: VideoFrames | None = None  # a video or camera: what was read, skipped as undecodable, or stopped

    def problems(self) -> list[str]:
        """What could not be read, one line each: a folder's images that could not be read at 8 bits (counted), a
        video's damaged stretches, a camera that stopped delivering frames."""
        lines = [f"{self.stem}: {len(self.skipped)} image(s) skipped, each named above"] if self.skipped else []
        if self.video is not None and self.video.skipped:
            lines.append(self.video.describe_skipped(self.stem))
        if self.video is not None and self.video.stopped_at is not None:
            lines.append(f"{self.stem} stopped delivering frames after {self.video.stopped_at}: is it still connected?")
        return lines


def overlay_names(images: list[Path]) -> dict[str, str]:
    """Overlay file names for a folder's images: ``<stem>.png``, or ``<stem>_<ext>.png`` where two
    images share a stem (a.png and a.jpg), so that every image gets its own overlay."""
    stems = Counter(p.stem for p in images)
    return {p.name: f"{p.stem}.png" if stems[p.stem] == 1 else f"{p.stem}_{p.suffix.lstrip('.').lower()}.png"
            for p in images}


def _folder_frames(images: list[Path], skipped: list[str]) -> Iterator[tuple[str, np.ndarray]]:
    """The folder's readable images; the others are reported on stderr and listed in ``skipped``."""
    for path in images:
        try:
            yield path.name, _read_image(path)
        except SourceError as error:
            skipped.append(f"{path.name}: {error}")
            print(f"skipping {path.name}: {error}", file=sys.stderr)


def _read_image(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise SourceError(f"cannot read image {path}: not an image file OpenCV can decode")
    return eight_bits(image, path.name)


def eight_bits(image: np.ndarray, name: str) -> np.ndarray:
    """An image file's pixels (as ``cv2.IMREAD_UNCHANGED`` decodes them) at 8 bits a channel, the detectors' input.

    16 bits: shifted right by the fewest bits that bring its brightest colour value within 255 (>> 8 for an image
    that uses the full range; >> 4 for a 12-bit sensor's data stored as it comes, which >> 8 would leave 16 grey
    levels: in a dim frame 2-4, where corners lose precision), never clipped. A float image in [0, 1]: scaled by 255.
    Any other depth, or floats beyond [0, 1], is refused (`SourceError`, with the fix): its scale is not known."""
    if image.dtype == np.uint8:
        return image
    if image.ndim == 3 and image.shape[2] == 4:
        image = np.ascontiguousarray(image[..., :3])  # alpha says nothing of the scene (and has its own scale)
    if image.dtype == np.uint16:
        shift = max(int(image.max()).bit_length() - 8, 0)
        return (image >> shift).astype(np.uint8)
    if np.issubdtype(image.dtype, np.floating):
        if not np.isfinite(image).all():
            raise SourceError(f"{name} is a {image.dtype} image with values that are not finite (NaN or inf): save it "
                              f"as an 8- or 16-bit image")
        low, high = float(image.min()), float(image.max())
        if low < 0.0 or high > 1.0:
            raise SourceError(f"{name} is a {image.dtype} image with values in [{low:g}, {high:g}], not [0, 1]: save it "
                              f"as an 8- or 16-bit image (or scaled to [0, 1])")
        return np.rint(image * 255.0).astype(np.uint8)
    raise SourceError(f"{name} is a {image.dtype} image: save it as an 8- or 16-bit (unsigned) image")


def _named(frames: VideoFrames) -> Iterator[tuple[str, np.ndarray]]:
    """A video's frames named by their number in the recording (a damaged stretch skipped leaves a gap)."""
    for index, frame in frames:
        yield str(index), frame


def open_source(source: str, max_frames: int | None = None) -> Source:
    """Image file, directory of images, video file, or an integer camera index."""
    if source.isdigit() and not Path(source).exists():
        capture = cv2.VideoCapture(int(source))
        if not capture.isOpened():
            raise SourceError(f"cannot open camera {source}: is it connected and not in use?")
        video = VideoFrames(capture, limit=max_frames, live=True)
        return Source(f"camera{source}", "camera", _named(video), capture.get(cv2.CAP_PROP_FPS) or 30.0, max_frames,
                      video=video)
    path = Path(source)
    if not path.exists():
        raise SourceError(f"{path} does not exist: give an image, a folder of images, a video or a camera index")
    if path.is_dir():
        images = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)[:max_frames]
        if not images:
            raise SourceError(f"{path} holds no images ({', '.join(sorted(IMAGE_SUFFIXES))})")
        skipped: list[str] = []
        return Source(path.name, "images", _folder_frames(images, skipped), 0.0, len(images), skipped,
                      overlay_names(images))
    if path.suffix.lower() in IMAGE_SUFFIXES:
        return Source(path.stem, "image", iter([(path.name, _read_image(path))]), 0.0, 1)
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        raise SourceError(f"cannot open {path} as a video: unknown format or codec")
    # Frames as stored, as images are read (no EXIF rotation): a phone video's rotation tag is not applied, on every
    # OpenCV build alike (some apply it by default), so corners stay in the grid its camera file was calibrated in.
    capture.set(cv2.CAP_PROP_ORIENTATION_AUTO, 0)
    video = VideoFrames(capture, limit=max_frames)
    count = video.count
    total = min(count, max_frames) if count and max_frames else count or max_frames
    return Source(path.stem, "video", _named(video), capture.get(cv2.CAP_PROP_FPS) or 30.0, total, video=video)


def frame_numbers(source: Source) -> Iterator[tuple[int, str, np.ndarray]]:
    """(frame number, name, BGR or grey image) of ``source``'s frames: the number is the frame's place in the
    recording, whatever was skipped before it: a video's (and a camera's) frame number (`VideoFrames` keeps it
    past a damaged stretch), a folder's image's place in its sorted listing (an unreadable image keeps its
    number), 0 for a single image. A rig pairs its cameras' frames by these (`deepcharuco.cli.calibrate_rig`)."""
    places = {name: k for k, name in enumerate(source.overlay_names)} if source.kind == "images" else {}
    for name, image in source.frames:
        yield places[name] if source.kind == "images" else int(name) if source.kind != "image" else 0, name, image
