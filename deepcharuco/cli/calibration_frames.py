"""The board found in calibration frames, one camera's or a rig's: each frame's detections as `FrameDetection`s
with their sharpness, detected in this process or on a `DetectorPool` (``calibrate --jobs``)."""

from __future__ import annotations

import sys
from functools import partial
from typing import Iterable

import numpy as np
from tqdm import tqdm

from deepcharuco.boards.board import BoardSpec
from deepcharuco.calibration.views import FrameDetection, sharpness
from deepcharuco.cli.common import jobs_warning
from deepcharuco.cli.detect import CHUNK_FRAMES, make_detector
from deepcharuco.detection.parallel import DetectorPool


def networks_of(args) -> str | None:
    """The networks a calibration's detector ran (``args.network``, resolved), or None for OpenCV's: the camera files'
    ``network`` node."""
    return None if args.detector == "opencv" else args.network


def calibration_detectors(name: str, boards: list[BoardSpec], refine: str, weights: str | None, network: str
                          ) -> list:
    """The detector ``name`` of each board, as `detect.make_detector` makes them (a worker process's finders)."""
    return [make_detector(name, board, refine, weights, network=network) for board in boards]


def calibration_pool(name: str, boards: list[BoardSpec], refine: str, weights: str | None, jobs: int,
                     network: str = "lite") -> DetectorPool | None:
    """``jobs`` worker processes, each with the detector ``name`` of each board (`calibration_detectors`); None for
    one job (the caller's detectors, in this process). Each frame is searched whole, as a photo is, in a worker as
    in this process (a fast-networks detector's lite backup searches the frames it searches in a photo)."""
    if jobs == 1:
        return None
    warning = jobs_warning(jobs)
    if warning:
        print(warning, file=sys.stderr)
    return DetectorPool(partial(calibration_detectors, name, boards, refine, weights, network), jobs,
                        chunk=CHUNK_FRAMES)


def detect_views(items: Iterable[tuple[tuple[int, int, str, np.ndarray], np.ndarray]], detectors: list,
                 cameras: int, pool: DetectorPool | None = None, total: int | None = None, quiet: bool = False
                 ) -> list[list[list[FrameDetection]]]:
    """Every board found in each ((camera, frame or instant, name, grey), grey) of ``items`` by ``detectors`` (one
    per board; or by ``pool``, whose finders are the same), as ``detections[camera][board]`` in the items' order,
    with a progress bar of frames (``total`` of them, when known)."""
    detections: list[list[list[FrameDetection]]] = [[[] for _ in detectors] for _ in range(cameras)]
    seen = [0] * cameras  # frames in which each camera found a board, for the progress bar
    with pool or DetectorPool(lambda: detectors) as detecting:
        bar = tqdm(detecting.detect(items), total=total, unit="frame", desc="detecting", disable=quiet)
        for (camera, index, name, gray), found in bar:
            for board, detection in enumerate(found):
                detections[camera][board].append(FrameDetection(index, name, detection.ids, detection.corners,
                                                                sharpness(gray, detection.corners),
                                                                detection.covariances))
            seen[camera] += any(len(d.ids) for d in found)
            bar.set_postfix(boards="/".join(map(str, seen)), refresh=False)
    return detections
