"""Truth for a capture set, in order: its labels file; the paper's auto-labelling of each video whose camera
and board stand still (`evaluate.paper.autolabel`); otherwise none. `SetTruth.description` says which, and why."""

from __future__ import annotations

import sys
from dataclasses import dataclass, field

import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.core.detection import Detection
from deepcharuco.geometry.pose import estimate_pose
from evaluate.captures.reader import (
    CaptureError, CaptureFrame, CaptureSet, Medium, absent_frames, read_labels, video_frames,
)
from evaluate.paper.autolabel import AVERAGE_FRAMES, AutolabelError, autolabel


@dataclass(frozen=True)
class FrameTruth:
    """One frame's truth: ``corners`` (C, 2) float32 by corner ID (NaN: not labelled), ``visible`` (C,) bool
    (the labelled ones), and the board pose (rvec, tvec (3,)) of those corners with the frame's camera, or
    None without a camera (or with fewer than 4 labelled corners)."""

    corners: np.ndarray
    visible: np.ndarray
    rvec: np.ndarray | None = None
    tvec: np.ndarray | None = None


@dataclass
class SetTruth:
    """``kind``: "labels", "autolabel" or "none"; ``notes``: one line per source of truth or reason for none;
    ``by_frame``: frame name -> (C, 2) corners (labels file); ``by_medium``: video file name -> its
    auto-labels (one static truth for every frame)."""

    kind: str
    notes: list[str]
    board: BoardSpec
    by_frame: dict[str, np.ndarray] = field(default_factory=dict)
    by_medium: dict[str, object] = field(default_factory=dict)

    @property
    def description(self) -> str:
        return "; ".join(self.notes)

    def for_frame(self, frame: CaptureFrame) -> FrameTruth | None:
        if self.kind == "labels":
            corners = self.by_frame.get(frame.name)
            return None if corners is None else _with_pose(corners, frame, self.board)
        labels = self.by_medium.get(frame.medium.path.name)
        if labels is None:
            return None
        return FrameTruth(labels.corners, labels.visible, labels.rvec, labels.tvec)

    def drop_medium(self, medium: Medium, reason: str) -> None:
        """Withdraw a video's auto-labels (its board moved after the averaged frames)."""
        if self.by_medium.pop(medium.path.name, None) is not None:
            self.notes.append(f"{medium.path.name}: auto-labels withdrawn, {reason}")
            if not self.by_medium:
                self.kind = "none"


def build_truth(captures: CaptureSet, average: int = AVERAGE_FRAMES) -> SetTruth:
    """The set's truth (module docstring). Auto-labelling reads the first ``average`` frames of each video
    that has a camera file into memory (30 frames of 1280x720: 28 MB)."""
    if captures.labels is not None:
        labels = read_labels(captures.labels, captures.board)
        foreign = absent_frames(captures, labels)
        example = ", ".join(repr(name) for name in foreign[:3])
        if labels and len(foreign) == len(labels):
            raise CaptureError(f"{captures.labels} labels {len(labels)} frame(s), none of them in {captures.folder} "
                               f"(e.g. {example}): name frames by the photo's file name or <video file name>#<frame "
                               f"number from 0>")
        notes = [f"{captures.labels.name}: {len(labels) - len(foreign)} labelled frames"]
        if foreign:
            notes.append(f"{len(foreign)} labelled frame(s) are not in the set and are ignored (e.g. {example})")
            print(f"warning: {captures.labels}: {notes[-1]}", file=sys.stderr)
        return SetTruth("labels", notes, captures.board, by_frame={n: c for n, c in labels.items() if n not in foreign})
    notes, by_medium = ["no labels.csv"], {}
    for medium in captures.media:
        if medium.kind == "image":
            continue
        if medium.camera is None:
            notes.append(f"{medium.path.name}: no camera file, so no auto-labels")
            continue
        frames = np.stack([image for _, image in video_frames(medium.path, 1, average)])
        camera = medium.camera.for_image_size(frames.shape[2], frames.shape[1])
        try:
            labels = autolabel(frames, camera.K, camera.dist, captures.board, average=average,
                               sequence=medium.path.name, source=str(medium.path))
        except AutolabelError as error:
            notes.append(f"no auto-labels: {': '.join(str(error).split(': ')[:2])}")  # what, not the CLI's advice
            continue
        by_medium[medium.path.name] = labels
        notes.append(f"{medium.path.name}: auto-labelled (the paper's recipe), {labels.describe()}")
    if any(m.kind == "image" for m in captures.media):
        notes.append("photos: each shows another view, and auto-labelling needs a still camera and board")
    return SetTruth("autolabel" if by_medium else "none", notes, captures.board, by_medium=by_medium)


def _with_pose(corners: np.ndarray, frame: CaptureFrame, board: BoardSpec) -> FrameTruth:
    visible = np.all(np.isfinite(corners), axis=1)
    if frame.camera is None or visible.sum() < 4:
        return FrameTruth(corners, visible)
    ids = np.flatnonzero(visible)
    labelled = Detection(ids=ids, corners=corners[ids], scores=np.ones(len(ids), np.float32))
    pose = estimate_pose(labelled, frame.camera.K, frame.camera.dist, board=board)
    return FrameTruth(corners, visible, None if pose is None else pose.rvec, None if pose is None else pose.tvec)
