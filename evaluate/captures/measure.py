"""Detectors on real capture sets, judged without full truth (and with it when there is some).

Per frame and detector:
- **found**: at least 4 corners (enough for a pose);
- **verified**: at least 6 corners that fit one view of the board: a RANSAC homography to 3 px, spread over
  the board, not mirrored (`board_check.fit_board_homography`), or, with a camera file, a PnP pose of 6 or
  more inliers whose eps_re (mean reprojection error, lens distortion included) is below 3 px;
- **agreement with OpenCV** where OpenCV + cornerSubPix finds at least 6 corners (the reference): the paper's
  accuracy with OpenCV's corners as the truth (same ID within 3 px, over OpenCV's corners), and **wrong IDs**:
  corners whose ID lands more than half a square (the local square side, from OpenCV's corners) from
  OpenCV's corner of that ID;
- **only**: frames one detector finds (>= 4 corners) and OpenCV does not, and the reverse;
- ms per frame (detection only);
- with truth (`truth`): the paper's corner accuracy (right ID within 3 px, over the labelled corners), pose
  accuracy (eps_re < 3 px) and confidently wrong poses (> 10 degrees or 10 % of the distance from the truth);
- with a by-eye review (frames_review.csv): of the frames OpenCV missed, how many each finds, per verdict.
"""

from __future__ import annotations

import heapq
import inspect
import time
from dataclasses import dataclass, field

import cv2
import numpy as np
from tqdm import tqdm

from deepcharuco.boards.board import BoardSpec
from deepcharuco.core.detection import Detection
from deepcharuco.detection.board_check import MIN_CONSENSUS, TOLERANCE_PX, fit_board_homography
from deepcharuco.detection.metrics import CORRECT_RADIUS_PX, match_corners
from deepcharuco.detection.opencv_detector import OpenCVDetector
from deepcharuco.geometry.camera import Camera
from deepcharuco.geometry.pose import estimate_pose
from evaluate.captures.reader import MIN_FOUND, CaptureFrame, CaptureSet
from evaluate.captures.truth import FrameTruth, SetTruth, build_truth
from evaluate.paper.protocols import (
    POSE_THRESHOLD_PX, WRONG_ROTATION_DEG, WRONG_TRANSLATION_FRACTION, DetectorLike, rotation_error_deg,
)

REFERENCE = "opencv"
MIN_REFERENCE = MIN_CONSENSUS  # OpenCV corners that make a frame a reference for agreement
WRONG_ID_SQUARES = 0.5  # a corner this many local square sides from OpenCV's corner of its ID has a wrong ID
GALLERY_WIDTH = 480  # px of each detector's panel in the gallery


@dataclass
class FrameMeasure:
    """One frame through every detector: ``found`` corners, ``verified``, ``eps_re`` (px, None without a
    pose), ``ms``, and against OpenCV (None where OpenCV has < 6 corners): ``agree`` (corners within 3 px),
    ``wrong`` (wrong IDs), ``compared`` (IDs both have), ``reference`` (OpenCV's corners); ``truth``: the
    paper's metrics per detector when the frame has truth."""

    name: str
    medium: str
    review: str | None
    found: dict[str, int] = field(default_factory=dict)
    verified: dict[str, bool] = field(default_factory=dict)
    eps_re: dict[str, float | None] = field(default_factory=dict)
    ms: dict[str, float] = field(default_factory=dict)
    agree: dict[str, int] = field(default_factory=dict)
    wrong: dict[str, int] = field(default_factory=dict)
    compared: dict[str, int] = field(default_factory=dict)
    agree_px: dict[str, list[float]] = field(default_factory=dict)
    reference: int = 0
    truth: dict[str, dict] = field(default_factory=dict)

    def to_dict(self) -> dict:
        record = {"frame": self.name, "found": self.found, "verified": self.verified,
                  "eps_re": {k: None if v is None else round(v, 4) for k, v in self.eps_re.items()},
                  "ms": {k: round(v, 1) for k, v in self.ms.items()}}
        if self.review is not None:
            record["review"] = self.review
        if self.reference:
            record.update(reference=self.reference, agree=self.agree, wrong=self.wrong)
        if self.truth:
            record["truth"] = self.truth
        return record


def build_detectors(board: BoardSpec, weights: str | None = None, refine_weights: str | None = None,
                    device: str = "cpu", network: str = "lite") -> dict[str, DetectorLike]:
    """OpenCV + cornerSubPix, the deep detector (when there are weights: given, or shipped), and its hybrid
    mode when this version's `Detector` has one (``mode="hybrid"``); ``network``: `Detector`'s, where not "lite"."""
    from deepcharuco.detection.deep_detector import DEFAULT_WEIGHTS, Detector

    detectors: dict[str, DetectorLike] = {REFERENCE: OpenCVDetector(board, refine="subpix")}
    if weights is None and not DEFAULT_WEIGHTS.is_file():
        return detectors
    options = {} if network == "lite" else {"network": network}  # a version before the fast networks takes none
    detectors["deep"] = Detector(board=board, weights=weights, refine_weights=refine_weights, device=device, **options)
    if "mode" in inspect.signature(Detector).parameters:
        detectors["hybrid"] = Detector(board=board, weights=weights, refine_weights=refine_weights, device=device,
                                       mode="hybrid", **options)
    return detectors


def verify(detection: Detection, board: BoardSpec, camera: Camera | None, width: int) -> tuple[bool, float | None]:
    """(verified, eps_re or None): see the module docstring. ``width``: the image's, to look at a mirrored
    board's corners from its printed side."""
    if len(detection) < MIN_CONSENSUS:
        return False, None
    if camera is not None:
        pose = estimate_pose(detection, camera.K, camera.dist, board=board, min_inliers=MIN_CONSENSUS)
        if pose is None:
            return False, None
        return pose.reprojection_error < POSE_THRESHOLD_PX, pose.reprojection_error
    pixels = detection.corners.astype(np.float64)
    if board.mirrored:  # seen from its printed side the board keeps its handedness, which the fit insists on
        pixels = np.c_[(width - 1) - pixels[:, 0], pixels[:, 1]]
    view = fit_board_homography(board.corner_points()[detection.ids, :2], pixels, TOLERANCE_PX, MIN_CONSENSUS)
    return view is not None, None


def local_square_px(reference: Detection, board: BoardSpec) -> np.ndarray:
    """(N,) the side of a board square in pixels around each of ``reference``'s (N >= 2) corners: the
    image distance to its two nearest corners on the board over their distance on the board."""
    xy = board.corner_points()[reference.ids, :2].astype(np.float64)
    on_board = np.linalg.norm(xy[:, None] - xy[None], axis=2)
    in_image = np.linalg.norm(reference.corners[:, None].astype(np.float64) - reference.corners[None], axis=2)
    np.fill_diagonal(on_board, np.inf)
    nearest = np.argsort(on_board, axis=1)[:, :2]
    rows = np.arange(len(xy))[:, None]
    return board.square_length * np.mean(in_image[rows, nearest] / on_board[rows, nearest], axis=1)


def compare_with_reference(detection: Detection, reference: Detection, board: BoardSpec
                           ) -> tuple[int, int, int, np.ndarray]:
    """(corners within 3 px of OpenCV's, wrong IDs, IDs compared, (K,) distances of those within 3 px)."""
    common, mine, theirs = np.intersect1d(detection.ids, reference.ids, return_indices=True)
    if len(common) == 0:
        return 0, 0, 0, np.zeros(0)
    distance = np.linalg.norm(detection.corners[mine].astype(np.float64) - reference.corners[theirs], axis=1)
    square = local_square_px(reference, board)[theirs]
    within = distance <= CORRECT_RADIUS_PX
    return int(within.sum()), int((distance > WRONG_ID_SQUARES * square).sum()), len(common), distance[within]


def score_truth(detection: Detection, truth: FrameTruth, board: BoardSpec, camera: Camera | None) -> dict:
    """The paper's metrics against a frame's truth: ``accuracy`` (right ID within 3 px / labelled corners),
    and with a camera ``eps_re`` (None: no pose) and ``wrong_pose`` (needs the true pose)."""
    match = match_corners(detection, truth.corners, truth.visible)
    scored = {"accuracy": match.num_correct / max(int(truth.visible.sum()), 1)}
    if camera is None:
        return scored
    pose = estimate_pose(detection, camera.K, camera.dist, board=board)
    scored["eps_re"] = None if pose is None else pose.reprojection_error
    wrong = False
    if pose is not None and truth.rvec is not None:
        translation = np.linalg.norm(pose.tvec - truth.tvec) / max(float(np.linalg.norm(truth.tvec)), 1e-9)
        wrong = rotation_error_deg(pose.rvec, truth.rvec) > WRONG_ROTATION_DEG or translation > WRONG_TRANSLATION_FRACTION
    scored["wrong_pose"] = bool(wrong)
    return scored


def measure_frame(frame: CaptureFrame, detectors: dict[str, DetectorLike], board: BoardSpec,
                  truth: FrameTruth | None) -> tuple[FrameMeasure, dict[str, Detection]]:
    """Every detector on one frame (OpenCV first: it is the reference) -> the measures and the detections."""
    measure = FrameMeasure(frame.name, frame.medium.path.name, frame.review)
    detections: dict[str, Detection] = {}
    for name, detector in detectors.items():
        started = time.perf_counter()
        detection = detector.detect(frame.image)
        measure.ms[name] = 1000.0 * (time.perf_counter() - started)
        detections[name] = detection
        measure.found[name] = len(detection)
        measure.verified[name], measure.eps_re[name] = verify(detection, board, frame.camera, frame.image.shape[1])
        if truth is not None:
            measure.truth[name] = score_truth(detection, truth, board, frame.camera)
    reference = detections[REFERENCE]
    if len(reference) >= MIN_REFERENCE:
        measure.reference = len(reference)
        for name, detection in detections.items():
            agree, wrong, compared, distances = compare_with_reference(detection, reference, board)
            measure.agree[name], measure.wrong[name], measure.compared[name] = agree, wrong, compared
            measure.agree_px[name] = distances.tolist()
    return measure, detections


def disagreement(measure: FrameMeasure) -> float:
    """How much a frame's detectors disagree with OpenCV (0: not at all): one verifies and the other not (3),
    wrong IDs (2), and the share of OpenCV's corners a detector misses."""
    score = 0.0
    for name in measure.found:
        if name == REFERENCE:
            continue
        score += 3.0 * (measure.verified[name] != measure.verified[REFERENCE])
        score += 2.0 * (measure.wrong.get(name, 0) > 0)
        if measure.reference:
            score += 1.0 - measure.agree[name] / measure.reference
    return score


def summarize(measures: list[FrameMeasure], name: str) -> dict:
    """One detector's numbers over a set's frames (module docstring)."""
    frames = len(measures)
    reference = [m for m in measures if m.reference]
    eps = [m.eps_re[name] for m in measures if m.verified[name] and m.eps_re[name] is not None]
    distances = [d for m in reference for d in m.agree_px[name]]
    found = np.array([m.found[name] >= MIN_FOUND for m in measures])
    found_cv = np.array([m.found[REFERENCE] >= MIN_FOUND for m in measures])
    summary = {
        "frames": frames, "corners": int(sum(m.found[name] for m in measures)), "found": int(found.sum()),
        "verified": int(sum(m.verified[name] for m in measures)),
        "mean_eps_re": float(np.mean(eps)) if eps else None,
        "reference_frames": len(reference),
        "accuracy_vs_opencv": float(np.mean([m.agree[name] / m.reference for m in reference])) if reference else None,
        "median_px_vs_opencv": float(np.median(distances)) if distances else None,
        "compared_corners": int(sum(m.compared[name] for m in reference)),
        "wrong_ids": int(sum(m.wrong[name] for m in reference)),
        "wrong_id_frames": int(sum(m.wrong[name] > 0 for m in reference)),
        "only_this": int((found & ~found_cv).sum()), "only_opencv": int((found_cv & ~found).sum()),
        "ms_per_frame": float(np.mean([m.ms[name] for m in measures])) if measures else None,
    }
    reviewed = [m for m in measures if m.review is not None]
    if reviewed:
        summary["review"] = {verdict: [int(sum(m.found[name] >= MIN_FOUND for m in reviewed if m.review == verdict)),
                                       sum(m.review == verdict for m in reviewed)]
                             for verdict in sorted({m.review for m in reviewed})}
    truthful = [m.truth[name] for m in measures if name in m.truth]
    if truthful:
        summary["truth"] = {"frames": len(truthful), "corner_accuracy": float(np.mean([t["accuracy"] for t in truthful]))}
        if "eps_re" in truthful[0]:
            summary["truth"]["pose_accuracy"] = float(np.mean([t["eps_re"] is not None and t["eps_re"] < POSE_THRESHOLD_PX
                                                               for t in truthful]))
            summary["truth"]["confidently_wrong"] = int(sum(t["wrong_pose"] for t in truthful))
    return summary


@dataclass(order=True)
class GalleryFrame:
    """A frame kept for the gallery: its ``score`` (`disagreement`), the image reduced to `GALLERY_WIDTH`
    and every detector's detection in that reduced image."""

    score: float
    order: int
    name: str = field(compare=False)
    image: np.ndarray = field(compare=False, repr=False)
    detections: dict[str, Detection] = field(compare=False, repr=False)
    measure: FrameMeasure = field(compare=False, repr=False)


def reduced(image: np.ndarray, detections: dict[str, Detection], width: int = GALLERY_WIDTH
            ) -> tuple[np.ndarray, dict[str, Detection]]:
    """The image scaled to ``width`` px (area-averaged; never enlarged) and the detections with it (OpenCV
    pixel centres at both sizes)."""
    scale = min(1.0, width / image.shape[1])
    if scale == 1.0:
        return image, detections
    small = cv2.resize(image, (width, max(1, round(image.shape[0] * scale))), interpolation=cv2.INTER_AREA)
    return small, {name: Detection(d.ids, (d.corners + 0.5) * scale - 0.5, d.scores) for name, d in detections.items()}


def evaluate_capture_set(captures: CaptureSet, detectors: dict[str, DetectorLike], step: int = 1,
                         limit: int | None = None, gallery: int = 3, quiet: bool = True
                         ) -> tuple[dict, list[GalleryFrame]]:
    """Every detector on the set's frames (``captures.frames(step, limit)``) -> (the set's results, the
    ``gallery`` frames where they disagree most, most first). Holds one full frame at a time."""
    if REFERENCE not in detectors:
        raise ValueError(f"the detectors must include {REFERENCE!r}, the reference")
    truth = build_truth(captures)
    measures: list[FrameMeasure] = []
    kept: list[GalleryFrame] = []
    for frame in tqdm(captures.frames(step, limit), desc=captures.name, unit="frame", disable=quiet):
        frame_truth = truth.for_frame(frame)
        measure, detections = measure_frame(frame, detectors, captures.board, frame_truth)
        if frame_truth is not None and truth.kind == "autolabel":
            _check_still(truth, frame, detections[REFERENCE], frame_truth)
        measures.append(measure)
        score = disagreement(measure)
        if gallery and score > 0:
            image, small = reduced(frame.image, detections)
            entry = GalleryFrame(score, -len(measures), frame.name, image, small, measure)
            (heapq.heappush if len(kept) < gallery else heapq.heappushpop)(kept, entry)
    if truth.kind != "labels":  # frames of a video whose auto-labels were withdrawn have no truth
        for m in measures:
            if m.medium not in truth.by_medium:
                m.truth = {}
    names = list(detectors)
    result = {"set": captures.name, "folder": str(captures.folder), "board": captures.board.to_dict(),
              "media": [m.path.name for m in captures.media], "camera": captures.has_camera,
              "truth": truth.kind, "truth_notes": truth.notes, "review": bool(captures.review),
              "problems": captures.problems,
              "step": step, "limit": limit,
              "detectors": {name: summarize(measures, name) for name in names},
              "frames": [m.to_dict() for m in measures]}
    return result, sorted(kept, reverse=True)


def _check_still(truth: SetTruth, frame: CaptureFrame, found: Detection, frame_truth: FrameTruth) -> None:
    """Auto-labels hold only while the board stays where the averaged frames saw it: withdraw a video's
    when OpenCV puts its corners (median) more than the recipe's 1 px from them in a later frame."""
    from evaluate.paper.autolabel import MAX_MOTION_PX

    known = frame_truth.visible[found.ids] if len(found) else np.zeros(0, bool)
    if known.sum() == 0:
        return
    moved = float(np.median(np.linalg.norm(found.corners[known] - frame_truth.corners[found.ids[known]], axis=1)))
    if moved > MAX_MOTION_PX:
        truth.drop_medium(frame.medium, f"the board moves by {moved:.1f} px in {frame.name}")
