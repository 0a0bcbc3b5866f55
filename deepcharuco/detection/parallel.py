"""Detection spread over worker processes: a video, a folder or a camera's frames detected on several cores
(and, on a GPU, by several processes feeding it), the results returned in the frames' order.

One process runs the deep detector's decoding (numpy, one core) after each network pass, so a frame takes the
network's time plus the decoding's whichever device runs the network: on a GPU the network is ~1 ms of a
frame and the decoding all the rest. Frames are independent, so ``workers`` processes, each with its own
detector, go through ``workers`` times as many frames a second where the cores are there (`benchmarks/
throughput.py` measures it).

Consecutive frames go to a worker in chunks of ``chunk``; where the finders track (`BoardTracker`), each chunk
is tracked from its first frame, which is searched whole. Where that loses a board the chunk before ended on (a
tracker had it in the chunk before's last frame and has none in this chunk's first), the chunk is tracked again
from that board before it is answered, as one process tracks it (the whole-frame refreshes then come at other
frames). A worker's network runs on cpu_count / workers
threads, so that the workers do not fight over the cores.
"""

from __future__ import annotations

import os
import signal
import sys
from collections import deque
from concurrent.futures import Future, ProcessPoolExecutor
from itertools import islice
from multiprocessing import get_context
from typing import Any, Callable, Iterable, Iterator, Sequence

import cv2
import numpy as np

from deepcharuco.core.detection import Detection
from deepcharuco.core.errors import OptionError
from deepcharuco.core.platform import available_cpus
from deepcharuco.detection.tracking import MIN_CORNERS

# Chunks given out ahead per worker: enough to keep each one busy while the caller reads frames, few enough that
# a long video is never held in memory.
AHEAD_PER_WORKER = 2

_finders: list[Any] = []  # a worker's own finders, made once by its initializer


def _start_worker(make_finders: Callable[[], Sequence[Any]], threads: int) -> None:
    # Before any network is made: ONNX Runtime and PyTorch take their thread counts from these (`network_threads`).
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the caller's: it stops giving out frames and closes
    os.environ["OMP_NUM_THREADS"] = str(threads)
    cv2.setNumThreads(threads)  # OpenCV's own pool: as many threads as cores in every worker would fight
    torch = sys.modules.get("torch")  # unpickling make_finders may have imported it already
    if torch is not None:
        torch.set_num_threads(threads)
    _finders[:] = list(make_finders())


def _detect_chunk(frames: list[np.ndarray]) -> list[list[Detection]]:
    for finder in _finders:
        if hasattr(finder, "reset"):  # a tracker: this chunk does not follow the last one this worker saw
            finder.reset()
    each = [detect_all(finder, frames) for finder in _finders]
    return [list(row) for row in zip(*each)]


def _continue_chunk(frames: list[np.ndarray], before: list[Detection], earlier: list[Detection]
                    ) -> list[list[Detection] | None]:
    """Each finder's detections of ``frames`` tracked on from ``before`` (its board in the frame before the chunk)
    and ``earlier`` (in the frame before that: the board's motion), as one process tracks them; None for a finder
    that does not track or had no board there."""
    columns: list[list[Detection] | None] = []
    for finder, last, older in zip(_finders, before, earlier):
        if not hasattr(finder, "follow_from") or len(last) < MIN_CORNERS:
            columns.append(None)
            continue
        finder.reset()
        finder.follow_from(last, older)
        columns.append(detect_all(finder, frames))
    return columns


def detect_all(finder, frames: Iterable[np.ndarray]) -> list[Detection]:
    """``finder``'s detection of each of ``frames``, in order, as a whole video is detected: a tracker's `push`
    (every frame it holds back flushed at the end), another finder's ``detect``."""
    return [*(d for frame in frames for d in settled(finder, frame)), *flushed(finder)]


def settled(finder, image: np.ndarray) -> list[Detection]:
    """The detections ``image`` settles: a tracker's `push` (it may hold frames back to look back through them), or
    the finder's detection of it."""
    return finder.push(image) if hasattr(finder, "push") else [finder.detect(image)]


def flushed(finder) -> list[Detection]:
    """The detections a tracker still holds back (the video has ended); none for another finder."""
    return finder.flush() if hasattr(finder, "flush") else []


class DetectorPool:
    """Finders (detectors or `BoardTracker`s) on ``workers`` processes.

    Args:
        make_finders: a callable that returns the finders, called once by each worker (with ``workers`` > 1 it
            must pickle: a module-level function, or a ``functools.partial`` of one). Every frame is given to each
            finder in turn.
        workers: processes (>= 1). One runs the finders in this process, as a plain loop would.
        chunk: consecutive frames a worker takes at once (>= 1); 1 for a live camera (each frame as it comes).

    ``detect(items)`` yields, for each (key, image) in order, the key and its finders' detections.
    """

    def __init__(self, make_finders: Callable[[], Sequence[Any]], workers: int = 1, chunk: int = 16):
        if workers < 1 or chunk < 1:
            raise OptionError(f"workers and chunk must be >= 1, got workers={workers}, chunk={chunk}")
        self.workers, self.chunk = workers, chunk
        self._executor: ProcessPoolExecutor | None = None
        self._local: list[Any] | None = None
        if workers == 1:
            self._local = list(make_finders())
        else:
            # spawn, not fork: a forked copy of a process that holds ONNX Runtime's or PyTorch's threads can hang
            self._executor = ProcessPoolExecutor(
                max_workers=workers, mp_context=get_context("spawn"), initializer=_start_worker,
                initargs=(make_finders, max(1, available_cpus() // workers)))

    def detect(self, items: Iterable[tuple[Any, np.ndarray]]) -> Iterator[tuple[Any, list[Detection]]]:
        """(key, image) pairs -> (key, [each finder's `Detection`]) in the same order. The keys stay in this
        process (a frame's name, the colour frame to draw on); only the images travel to the workers."""
        if self._local is not None:
            yield from self._detect_here(items)
            return
        pending: deque[tuple[list[Any], list[np.ndarray], Future]] = deque()
        items = iter(items)
        before: list[Detection] | None = None  # each finder's detection in the last frame answered
        earlier: list[Detection] | None = None  # and in the frame before that
        try:
            while True:
                while len(pending) < AHEAD_PER_WORKER * self.workers:
                    chunk = list(islice(items, self.chunk))
                    if not chunk:
                        break
                    keys, images = zip(*chunk)
                    pending.append((list(keys), list(images), self._executor.submit(_detect_chunk, list(images))))
                if not pending:
                    return
                keys, images, future = pending.popleft()
                rows = future.result()
                if before is not None and self.chunk > 1:  # chunks of one frame (a camera's) are not tracked
                    rows = self._stitched(images, rows, before, earlier)
                earlier, before = (rows[-2] if len(rows) > 1 else before), rows[-1]
                yield from zip(keys, rows)
        finally:
            for *_, future in pending:
                future.cancel()

    def _stitched(self, images: list[np.ndarray], rows: list[list[Detection]], before: list[Detection],
                  earlier: list[Detection] | None) -> list[list[Detection]]:
        """``rows`` (a chunk's detections, frame by frame) with each tracker's tracked again from ``before`` where it
        had a board in the frame before the chunk and none in the chunk's first frame, the board's motion from
        ``earlier`` (the frame before that; None: not known) on."""
        lost = [len(last) >= MIN_CORNERS and len(first) < MIN_CORNERS for last, first in zip(before, rows[0])]
        if not any(lost):
            return rows
        again = [last if redo else Detection.empty() for last, redo in zip(before, lost)]
        older = [Detection.empty()] * len(before) if earlier is None else earlier
        columns = self._executor.submit(_continue_chunk, images, again, older).result()
        return [[row[f] if column is None else column[i] for f, column in enumerate(columns)]
                for i, row in enumerate(rows)]

    def _detect_here(self, items: Iterable[tuple[Any, np.ndarray]]) -> Iterator[tuple[Any, list[Detection]]]:
        """`detect` in this process: a frame is answered once every finder has settled it (a tracker looking back
        holds a few frames)."""
        keys: deque[Any] = deque()
        pending: list[deque[Detection]] = [deque() for _ in self._local]
        for key, image in items:
            keys.append(key)
            for finder, done in zip(self._local, pending):
                done.extend(settled(finder, image))
            while keys and all(pending):
                yield keys.popleft(), [done.popleft() for done in pending]
        for finder, done in zip(self._local, pending):
            done.extend(flushed(finder))
        while keys:
            yield keys.popleft(), [done.popleft() for done in pending]

    def close(self) -> None:
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None

    def __enter__(self) -> "DetectorPool":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
