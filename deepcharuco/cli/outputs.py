"""What `deepcharuco detect` writes into --out: a CSV row per frame as it arrives, the JSON at the end (also on
Ctrl-C), and the overlays (a PNG per image, an MP4 for a video or camera), each marked as the command's own so that
a user's file of that name is never replaced unasked. Pixels OpenCV's.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import cv2
import numpy as np

from deepcharuco.cli.sources import Source
from deepcharuco.core.detection import Detection, largest_sigmas
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.core.files import (
    mp4_marked, png_marked, temporary_name, write_atomic,
)
from deepcharuco.geometry.pose import Pose


CSV_FIELDS = ["frame", "source", "num_corners", "ids", "corners", "scores",
              "rvec", "tvec", "reprojection_error", "num_inliers", "sigmas", "time_s"]


# What a CSV of this command begins with, in this version and those before the sigmas column: safe to overwrite.
CSV_SIGNATURE = ",".join(CSV_FIELDS[:6])


def frame_record(index: int, name: str, detection: Detection, pose: Pose | None, time_s: float | None = None) -> dict:
    """One frame's JSON record: ``index`` its number in the recording, ``time_s`` its time (a video's or a camera's
    frames: `video.VideoFrames.times`; None for images)."""
    record = {"frame": index, "source": name, "time_s": time_s, "num_corners": len(detection), **detection.to_dict()}
    record["pose"] = None if pose is None else pose.to_dict()
    return record


def joined(values) -> str:
    return " ".join(f"{v:g}" for v in values)


def csv_row(record: dict) -> dict:
    """One CSV row per frame: lists as space-separated numbers, corners as x0 y0 x1 y1 ..."""
    pose = record["pose"] or {}
    return {
        "frame": record["frame"], "source": record["source"], "num_corners": record["num_corners"],
        "ids": " ".join(str(i) for i in record["ids"]),
        "corners": joined(np.ravel(record["corners"])), "scores": joined(record["scores"]),
        "rvec": joined(pose.get("rvec", [])), "tvec": joined(pose.get("tvec", [])),
        "reprojection_error": pose.get("reprojection_error", ""),
        "num_inliers": len(pose["inliers"]) if pose else "",
        # each corner's standard deviation along its least certain direction (px); nan where none is given
        "sigmas": joined(largest_sigmas([[[c[0], c[1]], [c[1], c[2]]] if c else [[math.nan] * 2] * 2
                                        for c in record["covariances"]])),
        "time_s": "" if record.get("time_s") is None else f"{record['time_s']:.6f}",
    }


# How every detection JSON of this command begins: what a rerun may overwrite without --force.
JSON_START = b'{"board": '


# The mark inside every overlay this command writes (a PNG text chunk, an MP4 free box): a rerun replaces only those
# without --force.
OVERLAY_MARK = "deepcharuco detect overlay"


class Overlays:
    """The overlay of each frame: a PNG per image (each written whole or not at all), or one MP4 for a video or
    camera, written under a temporary name and renamed into place only when it reads back complete."""

    def __init__(self, out: Path, source: Source):
        self.out, self.source = out, source
        self.writer: cv2.VideoWriter | None = None
        self.video = out / f"{source.stem}_overlay.mp4"
        self.written = 0

    def video_path(self) -> Path | None:
        """The overlay MP4 this source's frames would be written to (None for images)."""
        return None if self.source.kind in ("image", "images") else self.video

    def images(self) -> list[Path]:
        """The overlay PNGs this source's frames would be written to (none for a video or camera)."""
        if self.source.kind == "image":
            return [self.out / f"{self.source.stem}_overlay.png"]
        if self.source.kind == "images":
            return [self.out / f"{self.source.stem}_overlay" / name for name in self.source.overlay_names.values()]
        return []

    def add(self, name: str, overlay: np.ndarray) -> None:
        if self.source.kind == "image":
            write_image(self.out / f"{self.source.stem}_overlay.png", overlay)
        elif self.source.kind == "images":
            folder = self.out / f"{self.source.stem}_overlay"
            folder.mkdir(exist_ok=True)
            write_image(folder / self.source.overlay_names[name], overlay)
        else:
            if self.writer is None:
                self.writer = cv2.VideoWriter(str(temporary_name(self.video)), cv2.VideoWriter_fourcc(*"mp4v"),
                                              self.source.fps, (overlay.shape[1], overlay.shape[0]))
                if not self.writer.isOpened():
                    self.writer = None
                    raise DeepCharucoError(f"cannot write the overlay video {self.video}: choose a writable --out "
                                           f"with free space, or pass --no-overlay")
            self.writer.write(overlay)
            self.written += 1

    def close(self, keep: bool) -> None:
        """Finish the overlay video: renamed into place when it reads back with every frame written, else
        removed and reported (OpenCV's video writer does not report a full disk itself)."""
        if self.writer is None:
            return
        self.writer.release()
        self.writer = None
        temporary = temporary_name(self.video)
        if not keep:
            temporary.unlink(missing_ok=True)
            return
        try:
            mp4_marked(temporary, OVERLAY_MARK)
        except (OSError, ValueError):
            pass  # left unmarked: a rerun asks for --force before replacing it, and loses nothing
        check = cv2.VideoCapture(str(temporary))
        frames = int(check.get(cv2.CAP_PROP_FRAME_COUNT)) if check.isOpened() else 0
        check.release()
        if frames != self.written:
            temporary.unlink(missing_ok=True)
            raise DeepCharucoError(f"could not write the overlay video {self.video} (is the disk full?): free some "
                                   f"space, choose another --out, or pass --no-overlay")
        os.replace(temporary, self.video)


def write_image(path: Path, image: np.ndarray) -> None:
    """The overlay image, whole or not at all (cv2.imwrite reports a full disk only by returning False)."""
    ok, encoded = cv2.imencode(path.suffix, image)
    if not ok:
        raise DeepCharucoError(f"could not encode the overlay {path}: pass --no-overlay")
    try:
        write_atomic(path, png_marked(encoded.tobytes(), OVERLAY_MARK), "the overlay")
    except DeepCharucoError as error:
        raise DeepCharucoError(f"{error} (or pass --no-overlay)") from None
