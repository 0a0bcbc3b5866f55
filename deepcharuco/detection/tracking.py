"""`BoardTracker`: in a video, search each frame only around the board found in the frame before.

A board moves little between frames, and on as it moved: the region around the previous frame's corners, each moved
on by its motion from the frame before that (`predicted`), widened by `MARGIN` of its size and at least
`MIN_MARGIN_SQUARES` corner spacings (for motion and for the markers beyond the outermost corners), holds it again;
the detector runs on that crop, which at 1280x720 with the board covering a quarter of the frame costs a quarter of the
pixels. (A hand-held board moves on: on caliscope's port_2 video the corners were found a median 0.10 corner spacings
from where the motion put them, 0.27 from the frame before's; the drawn validation videos' tracked frames found 7 %
more boards with the crop centred there.) A full-frame search runs when the crop finds nothing, when there was no
board before, and every ``refresh_every`` frames (a second board, or the board re-entering elsewhere, is never missed
for long); a refresh that finds nothing keeps the board the crop still finds. A detector that takes ``expected``
(`Detector`) is told where the motion puts the board: a board read by its markers is looked for first in that view,
verified by its markers as any view is.

While no board is tracked, ``search_every`` N > 1 searches the whole frame at every level only every N-th
frame, and the frames between at the coarse level alone (`Detector.detect`'s ``levels``): a board large
enough to be read there (squares of ~12 px or more at 320 px: a 5x5-square board a fifth of a 1280x720
frame's width) is found at once, a smaller one up to N - 1 frames late. A hybrid `Detector` looks with its networks
alone there: a board that only OpenCV reads is found by the next search of every level. A frame without a board costs
most (every level is searched, and twice for an inverted print in a dim frame); in a live camera's stream it is most
of the frames while the board is away.

An inverted print is searched again negated about its local white where a detector's first search finds nothing
(`Detector.detect`'s ``local_white``): under a shadow, or dim under a lamp, it shows there alone. The tracker's
whole-frame searches leave that second search out of lit frames and keep it in dim ones and in its crops: in a lit
frame without a board it doubled the cost, and in lit frames what it found was found from the neighbouring frames
(docs/detector.md, "An inverted print's second search left to the crops").

A whole video need not answer frame by frame: `BoardTracker.push` holds back the frames that found nothing (up to
`HOLD_BYTES` of them), and when a later frame finds the board, looks back through them, newest first, around the
board as if tracking it backwards, until one shows it no more; a frame whose search left something out (the coarse look
alone, or an inverted print's second search) is searched whole, with everything, there before the look back stops, as
a full search would have. A small board is then found in the frames a quicker search reached late, and a board a whole
search missed in one frame (blurred) is kept from the frame after it.

A `Detector` with the fast networks (``network`` "fast" or "auto") hands a crop they lose the board in to its lite
networks (`Detector.backup`): the tracker asks once, the detector answers with whichever found it. The tracker's
whole-frame searches are a stream's (`Detector.detect`'s ``stream``), as are a stream's frames searched whole without
a tracker (`StreamFrames`): there "fast" never lets the lite networks search a whole frame (in a dark video that
cost lite's whole search in every frame without the board) and in a dim one the fast networks find nothing in "auto"
has them search its full resolution whole (a 640x480 frame's, searched whole already: the lite networks; a photo gets
more: `deep_detector.WHOLE_BACKUP`).
"""

from __future__ import annotations

import inspect

import numpy as np

from deepcharuco.core.detection import Detection, corner_spacing
from deepcharuco.core.errors import OptionError

MARGIN = 0.5  # of the corners' bounding box, on each side
MIN_MARGIN_SQUARES = 2.0  # corner spacings, on each side
MIN_CROP = 64  # px: smaller crops are widened to this
MIN_CORNERS = 4  # a crop's detection with fewer corners falls back to the full frame
HOLD_BYTES = 256 * 2 ** 20  # `push` holds back at most this many bytes of frames; beyond, the oldest is settled as is


class StreamFrames:
    """A detector's frames of a stream searched whole, one by one, without a tracker (a camera's frames on ``--jobs``
    workers, a video with ``--refresh-every 1``): as in a `BoardTracker`'s whole searches, a `Detector` is told each
    frame is a stream's (``stream``: its lite networks behind the fast ones search fewer whole frames)."""

    def __init__(self, detector):
        self.detector = detector
        self._options = _stream_options(detector)

    def detect(self, image: np.ndarray) -> Detection:
        return self.detector.detect(image, **self._options)


def search_region(corners: np.ndarray, image_size: tuple[int, int]) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1), exclusive ends, of the crop to search the next frame in, around (N, 2) ``corners``
    (N >= 2), inside an image of ``image_size`` (W, H)."""
    limits = np.array(image_size, np.float64)
    low, high = corners.min(axis=0), corners.max(axis=0)
    margin = np.maximum(MARGIN * (high - low), MIN_MARGIN_SQUARES * corner_spacing(corners))
    size = np.minimum(np.maximum(high - low + 2 * margin, MIN_CROP), limits)
    # Centred on the corners, moved (not cut) to stay inside the image, so a board at an edge keeps its margin.
    start = np.clip(np.floor((low + high - size) / 2), 0, limits - np.ceil(size))
    x0, y0 = (int(v) for v in start)
    x1, y1 = (int(v) for v in np.minimum(start + np.ceil(size), limits))
    return x0, y0, x1, y1


def predicted(last: Detection, before: Detection) -> Detection:
    """Where the corners of ``last`` (the board in the frame before) are expected in the next frame: each moved on
    by its own motion from ``before`` (the frame before that) to ``last``, a corner ``before`` lacks by their median
    motion. ``last`` itself where the two share fewer than `MIN_CORNERS` corners (no motion to go by), or where the
    median motion is no longer than the corners' own motions stray from it (a still board: its corners' jitter,
    carried on, would move the crop by noise, and a marginal board then comes and goes)."""
    shared, in_last, in_before = np.intersect1d(last.ids, before.ids, return_indices=True)
    if len(shared) < MIN_CORNERS:
        return last
    own = last.corners[in_last] - before.corners[in_before]
    median = np.median(own, axis=0)
    if np.hypot(*median) <= np.median(np.hypot(*(own - median).T)):
        return last
    motion = np.empty_like(last.corners)
    motion[:] = median
    motion[in_last] = own
    return Detection(ids=last.ids, corners=last.corners + motion, scores=last.scores)


def _stream_options(detector) -> dict:
    """``detect``'s keywords that say the frame is a stream's (`Detector.detect`'s ``stream``), where it takes them."""
    return {"stream": True} if _takes(detector, "stream") else {}


def _takes(detector, option: str) -> bool:
    """Whether ``detector.detect`` takes the keyword ``option`` (a coarse-to-fine `Detector`'s takes ``levels`` and
    ``expected``)."""
    try:
        return option in inspect.signature(detector.detect).parameters
    except (TypeError, ValueError):  # a detect without a readable signature (a compiled extension's)
        return False


class BoardTracker:
    """Wraps any detector (``detect(image) -> Detection``) for consecutive video frames.

    Args:
        detector: `Detector`, `OpenCVDetector`, ...
        refresh_every: a full-frame search at least every this many frames (1: always, no tracking).
        search_every: while no board is tracked, every level of the pyramid is searched every this many
            frames, the coarse level alone in the frames between (1: every level always; module docstring).
            Only for detectors whose ``detect`` takes ``levels`` (`Detector`); others search whole frames.
        look_back: `push` holds back the frames that found nothing, and looks back through them when a later frame
            finds the board (a whole video); False: `push` answers each frame at once (a live camera).
        predict_motion: the crop is centred on where the board will be if it moves on as it moved between the two
            frames before (`predicted`), and a detector that takes ``expected`` is told that place; False: where it
            was in the frame before.

    ``detect(image)`` returns corners in ``image``'s pixels, as the detector would; ``last_search`` says
    whether the last call searched the "crop", the "full" frame or the frame at the "coarse" level alone.
    ``push(image)`` / ``flush()`` do the same for a whole video, looking back (module docstring).
    """

    def __init__(self, detector, refresh_every: int = 30, search_every: int = 1, look_back: bool = True,
                 predict_motion: bool = True):
        if refresh_every < 1:
            raise OptionError(f"refresh_every must be >= 1 (1: a full-frame search every frame), got {refresh_every}")
        if search_every < 1:
            raise OptionError(f"search_every must be >= 1 (1: every level of every frame), got {search_every}")
        self.detector = detector
        getattr(detector, "backup", None)  # built now, not when the board is first lost (~0.6 s: a live camera stalls)
        self.refresh_every = refresh_every
        self.search_every = search_every if _takes(detector, "levels") else 1
        self.look_back = look_back
        self.predict_motion = predict_motion
        self._last = Detection.empty()  # the board found in the frame before
        self._before = Detection.empty()  # ... and in the frame before that
        self._takes_expected = _takes(detector, "expected")
        # Whole-frame searches leave an inverted print's second search (about its local white) out of lit frames
        # (module docstring); a print that is not inverted has none to leave out.
        inverted = bool(getattr(getattr(detector, "board", None), "inverted", False))
        self._whole_options = {"local_white": "dim"} if inverted and _takes(detector, "local_white") else {}
        # Its whole searches are a stream's: a fast-networks detector's lite backup searches fewer of them
        # (`deep_detector.WHOLE_BACKUP`; with network "fast", none: in a dark video the board is away in most of
        # those frames, and each cost lite's whole search, ~0.26 s at 720p; docs/detector.md).
        self._stream = _stream_options(detector)
        self._left_out = False  # whether the last whole-frame search left something out
        self._since_full = 0
        self._coarse_left = 0  # coarse-only searches before the next search of every level
        # `push`: the frames that found nothing (image, detection, whether its search left something out)
        self._held: list[tuple[np.ndarray, Detection, bool]] = []
        self.last_search = "full"
        self.looked_back = 0  # frames `push` found the board in by looking back

    def reset(self) -> None:
        """Forget the board (a cut in the video): the next frame is searched whole, at every level. Frames `push`
        holds back are dropped: `flush` them first."""
        self._last = self._before = Detection.empty()
        self._coarse_left = 0
        self._held.clear()

    def follow_from(self, detection: Detection, before: Detection | None = None) -> None:
        """Track on from ``detection``, the board in the frame before the next one given (found by another tracker:
        a worker process's chunk continues the chunk before it), and ``before``, the board in the frame before that
        where known: the motion between the two carries on (`predicted`)."""
        self._last, self._before = detection, Detection.empty() if before is None else before
        self._since_full = 0
        self._coarse_left = 0

    def push(self, image: np.ndarray) -> list[Detection]:
        """The next frame of a whole video -> the detections it settles, oldest first: none while it is held back,
        else those of the frames held before it and its own. A frame is held back when it found nothing; when a later
        frame finds the board, the held frames are searched again, newest first, in the region around the board in
        the frame after each (as `detect` tracks forwards), and a frame the region does not show it in that had only
        the coarse look (``search_every`` > 1) is searched whole, until one finds it no more; those before it keep
        their empty detections. Frames beyond `HOLD_BYTES` are settled oldest first, as they are."""
        detection = self.detect(image)
        if not self.look_back:
            return [detection]
        if len(detection) < MIN_CORNERS:
            self._held.append((image, detection, self._left_out))
            return self._over_budget()
        settled = self._looked_back(detection)
        if settled:  # the frame before this one, as looking back found it: the board's motion into this frame
            self._before = settled[-1]
        self._held.clear()
        return [*settled, detection]

    def flush(self) -> list[Detection]:
        """The detections of the frames still held back (the video has ended), oldest first."""
        settled = [detection for _, detection, _ in self._held]
        self._held.clear()
        return settled

    def _over_budget(self) -> list[Detection]:
        """The oldest held frames' detections, settled as they are, until the rest fit `HOLD_BYTES`."""
        settled = []
        while len(self._held) > 1 and sum(image.nbytes for image, _, _ in self._held) > HOLD_BYTES:
            settled.append(self._held.pop(0)[1])
        return settled

    def _looked_back(self, found: Detection) -> list[Detection]:
        """The held frames' detections, oldest first, each held frame searched again from the newest back around
        the board in the frame after it (whole, with everything, where that fails and its search left something out),
        until one finds too few corners. The board is expected to move on backwards as it moved between the two frames
        after each."""
        later, after, revised = found, Detection.empty(), []
        for image, _, partial in reversed(self._held):
            around = self._around(image, later, after)
            if len(around) < MIN_CORNERS and partial:
                around = self.detector.detect(image, **self._stream)
            if len(around) < MIN_CORNERS:
                break
            later, after = around, later
            revised.append(later)
        self.looked_back += len(revised)
        kept = [detection for _, detection, _ in self._held[:len(self._held) - len(revised)]]
        return [*kept, *reversed(revised)]

    def detect(self, image: np.ndarray) -> Detection:
        self._since_full += 1
        refreshing = self._tracking and self._since_full >= self.refresh_every
        if self._tracking and not refreshing:
            detection = self._around(image, self._last, self._before)
            if len(detection) >= MIN_CORNERS:
                self._follow(detection)
                self.last_search, self._left_out = "crop", False
                return detection
            self._coarse_left = 0  # the board was just lost: it may have shrunk or left by an edge
        if not self._tracking and self._coarse_left > 0:
            self._coarse_left -= 1
            detection = self.detector.detect(image, levels=1)
            self._follow(detection)
            if self._tracking:
                self._since_full = 0
            self.last_search, self._left_out = "coarse", True
            return detection
        detection = self.detector.detect(image, **self._whole_options, **self._stream)
        self._left_out = bool(getattr(self.detector, "local_white_skipped", False))  # only "dim" leaves anything out
        self._since_full = 0
        if refreshing and len(detection) < MIN_CORNERS:
            # A refresh that finds nothing keeps the board the crop still finds: a still board half out of the frame,
            # which only tracking reads (cam_1's, caliscope), was dropped every refresh_every frames.
            around = self._around(image, self._last, self._before)
            if len(around) >= MIN_CORNERS:
                detection = around
                self._follow(detection)
                self.last_search, self._left_out = "crop", False
                return detection
        self._follow(detection)
        self._coarse_left = self.search_every - 1 if not self._tracking else 0
        self.last_search = "full"
        return detection

    def _around(self, image: np.ndarray, last: Detection, before: Detection) -> Detection:
        """The board in ``image`` (its pixels) found in the region (`search_region`) around where ``last``, the board in
        the frame next to it, moves on to from ``before``, the board in the frame next to that one on the same side
        (`predicted`, where `predict_motion`; else around ``last``)."""
        height, width = image.shape[:2]
        expected = predicted(last, before) if self.predict_motion else last
        x0, y0, x1, y1 = search_region(expected.corners, (width, height))
        found = self._detect_crop(image[y0:y1, x0:x1], max(height, width), (x0, y0), last, expected)
        return Detection(ids=found.ids, corners=found.corners + np.array([x0, y0], np.float32), scores=found.scores,
                         covariances=found.covariances)

    def _detect_crop(self, crop: np.ndarray, frame_longest: int, origin: tuple[int, int], last: Detection,
                     expected: Detection) -> Detection:
        """The detector on ``crop``, around ``last`` (the board in the frame next to it, in frame pixels); a
        coarse-to-fine `Detector` searches it from the scale its whole frame is searched at (its own choice, by the
        crop's size alone, would look at a nearly square crop of a board that fills the frame in more pixels than the
        whole frame), skipping the levels (twice that scale, four times ...) where the
        board's squares, as wide as in the frame before, would be narrower than half ``min_square_px``:
        there and at the next level they are too narrow to stop the search. The last level before they are wide
        enough is kept: caliscope's webcams show blurred boards that it reads (squares ~11 px) and full resolution
        (~22 px) does not (starting at the wide-enough level lost 4 of cam_1's 127 frames with a board, lit and dark).
        A `Detector` told where the board was searches that kept level only where the wide-enough one finds nothing
        (`Detector._expected_start`). A detector whose ``detect`` takes ``expected`` is told ``expected`` (in frame
        pixels: ``last``, or where `predicted` puts it) in the crop's pixels (its origin at ``origin`` in the frame)."""
        options = {}
        if self._takes_expected:
            options["expected"] = Detection(ids=expected.ids, corners=expected.corners - np.array(origin, np.float32),
                                            scores=expected.scores)
        working_size = getattr(self.detector, "working_size", None)
        if working_size is None:
            return self.detector.detect(crop, **options)
        spacing = corner_spacing(last.corners)
        longest = max(crop.shape[:2])
        size = max(1, round(min(1.0, working_size / frame_longest) * longest))
        min_square = getattr(self.detector, "min_square_px", None)
        if min_square is not None:
            while size < longest and 2 * spacing * size / longest < min_square:
                size = min(2 * size, longest)
        return self.detector.detect(crop, working_size=size, **options)

    @property
    def _tracking(self) -> bool:
        """Whether the frame before found the board (its crop is searched next)."""
        return len(self._last) >= MIN_CORNERS

    def _follow(self, detection: Detection) -> None:
        self._last, self._before = detection, self._last
