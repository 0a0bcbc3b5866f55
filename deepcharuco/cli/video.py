"""Reading a video's frames past damage: a stretch that cannot be decoded is skipped and counted, not
taken for the end of the file.

OpenCV's ``VideoCapture.read`` returns False both at the end of a file and at a frame its decoder
rejects (a damaged stretch of a recording); the frames after the damage read again. `VideoFrames`
keeps reading until the file's frame count is reached or `MAX_BAD_RUN` reads in a row fail, numbers
frames by their place in the video (so frame numbers stay those of the recording) and says what it
skipped. A live camera that stops delivering ends the stream at once.
"""

from __future__ import annotations

import time
from typing import Iterator

import cv2
import numpy as np
from deepcharuco.core.errors import OptionError

# Failed reads in a row after which a file is taken to have ended (about 10 s of 30 fps video): a damaged
# stretch longer than this ends the reading, and is reported as frames that could not be decoded.
MAX_BAD_RUN = 300


class VideoFrames:
    """(frame number, BGR image) of every ``step``-th frame of ``capture``, at most ``limit`` of them.

    Frames between the ``step``-th are grabbed, not decoded. After iterating, ``skipped`` holds the
    (first, last) frame numbers of each stretch that could not be decoded, ``read`` the frames
    yielded, and `describe_skipped` a line for the user (empty when nothing was skipped). The capture
    is released when the iteration ends. ``times`` holds each yielded frame's time in seconds: a file's
    presentation time (``CAP_PROP_POS_MSEC`` after the read: a variable frame rate's own), a live camera's
    seconds since its first frame arrived (this process' clock).
    """

    def __init__(self, capture: cv2.VideoCapture, *, step: int = 1, limit: int | None = None, live: bool = False):
        if step < 1 or (limit is not None and limit < 1):
            raise OptionError(f"step and limit must be >= 1, got step={step}, limit={limit}")
        self.capture, self.step, self.limit, self.live = capture, step, limit, live
        count = 0 if live else int(capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        self.count: int | None = count if count > 0 else None  # the container's frame count, when it says
        self.skipped: list[tuple[int, int]] = []
        self.read = 0
        self.stopped_at: int | None = None  # a live camera: the frame at which it stopped delivering
        self.times: dict[int, float] = {}  # frame number -> seconds (class docstring)
        self._start: float | None = None  # a live camera: when its first frame arrived

    def __iter__(self) -> Iterator[tuple[int, np.ndarray]]:
        index, bad_from = 0, None
        try:
            while self.limit is None or self.read < self.limit:
                wanted = index % self.step == 0
                if wanted:
                    ok, frame = self.capture.read()
                else:
                    ok, frame = self.capture.grab(), None
                if not ok:
                    if self.live:
                        self.stopped_at = index
                        return
                    bad_from = index if bad_from is None else bad_from
                    if index + 1 - bad_from >= MAX_BAD_RUN or (self.count is not None and index + 1 >= self.count):
                        if self.count is not None and bad_from < self.count:
                            self.skipped.append((bad_from, self.count - 1))  # the rest of what the file holds
                        return
                    index += 1
                    continue
                if bad_from is not None:
                    self.skipped.append((bad_from, index - 1))
                    bad_from = None
                if wanted:
                    self.read += 1
                    self.times[index] = self._time()
                    yield index, frame
                index += 1
        finally:
            self.capture.release()

    def _time(self) -> float:
        """The frame just read's time in seconds (``times``)."""
        if self.live:
            now = time.perf_counter()
            self._start = now if self._start is None else self._start
            return now - self._start
        return self.capture.get(cv2.CAP_PROP_POS_MSEC) / 1000.0

    @property
    def skipped_frames(self) -> int:
        return sum(last - first + 1 for first, last in self.skipped)

    def describe_skipped(self, name: str) -> str:
        """One line on the frames of ``name`` that could not be decoded (empty when none)."""
        if not self.skipped:
            return ""
        stretches = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in self.skipped[:5])
        more = f" and {len(self.skipped) - 5} more stretches" if len(self.skipped) > 5 else ""
        return (f"{name}: {self.skipped_frames} frame(s) could not be decoded and were skipped (frames {stretches}"
                f"{more}); the rest were read. A damaged recording: re-encode it (ffmpeg -i in.mp4 -c:v libx264 "
                f"out.mp4) to check")
