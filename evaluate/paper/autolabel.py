"""Auto-labelling of captures, the paper's recipe: ``python -m evaluate.paper.autolabel VIDEO --camera cam.yaml``.

A capture films a static board with a still camera. Its truth is OpenCV's detection
(+ cornerSubPix) on the average of its first 30 frames — averaging removes the sensor noise —
applied to every frame, and the pose of those corners (solvePnPRansac with the camera's K).
The result is a shard in the schema of docs/conventions.md that `evaluate.report --captures` evaluates.

The recipe is only right for a static board, so it refuses (`AutolabelError`, exit code 2,
nothing written) when the capture has fewer than 30 frames, when the board is not found in the
average (fewer than 4 corners, or no pose), or when the board moves during the averaged frames:
OpenCV runs on each of them, and a frame's displacement is the median distance of its corners
from the average's (a median, so one badly refined corner in a noisy frame is not motion).

VIDEO is a video file, a folder of images (sorted by name) or an HDF5 shard. A shard brings its
own K, and when it is a render (`evaluate.paper.sequences`, `datagen.render`) it carries the render
truth: then the auto-labels are compared with it (`compare_to_truth`), which measures the
recipe itself.
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from datagen.shards import FrameLabels, ShardReader, list_shards, write_shard
import deepcharuco
from deepcharuco.boards.board import BoardSpec
from deepcharuco.cli.common import output_folder, run_command
from deepcharuco.cli.sources import open_source
from deepcharuco.core.detection import Detection
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.core.image import to_gray_u8
from deepcharuco.detection.opencv_detector import OpenCVDetector
from deepcharuco.geometry.camera import read_camera
from deepcharuco.geometry.pose import estimate_pose
from evaluate.paper.protocols import rotation_error_deg

AVERAGE_FRAMES = 30
MAX_MOTION_PX = 1.0
MIN_CORNERS = 4
DIST_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4", "tx", "ty")


class AutolabelError(DeepCharucoError):
    """A capture the recipe cannot label truthfully (too short, no board, a moving board)."""


@dataclass
class Capture:
    """The frames of one input.

    Attributes:
        frames: (N, H, W) uint8 grayscale.
        name: the sequence's name (a shard's ``meta/sequence``, else the file or folder stem).
        source: the input path as given.
        kind: "video", "images" or "shard".
        K: (3, 3) intrinsics stored in a shard's first frame, else None.
        meta: a shard's per-frame meta (N dicts), else None.
        has_truth: True for a shard of renders (not one of auto-labels): it holds the true corners.
        shard_index: a shard's index (from its name), else None.
    """

    frames: np.ndarray
    name: str
    source: str
    kind: str
    K: np.ndarray | None = None
    meta: list[dict] | None = None
    has_truth: bool = False
    shard_index: int | None = None


def read_capture(source: str | Path, quiet: bool = True) -> Capture:
    """Read every frame of a video file, a folder of images or an HDF5 shard, as grayscale."""
    path = Path(source)
    if not path.exists():
        raise AutolabelError(f"{path} does not exist: give a video file, a folder of images or a shard-*.h5 file")
    if path.is_file() and path.suffix.lower() in (".h5", ".hdf5"):
        reader = ShardReader(path)
        try:
            count = len(reader)
            frames = [reader[i] for i in tqdm(range(count), desc="reading", unit="frame", disable=quiet)]
        finally:
            reader.close()
        meta = [f.meta for f in frames]
        name = str(meta[0].get("sequence", path.stem)) if meta else path.stem
        index = int(path.stem.split("-")[1]) if path.stem.startswith("shard-") and path.stem[6:].isdigit() else None
        return Capture(frames=np.stack([f.image for f in frames]), name=name, source=str(source), kind="shard",
                       K=np.asarray(frames[0].K, np.float64), meta=meta,
                       has_truth=bool(meta) and "autolabel_source" not in meta[0], shard_index=index)
    opened = open_source(str(path))
    images = [to_gray_u8(image) for _, image in tqdm(opened.frames, total=opened.total, desc="reading", unit="frame",
                                                      disable=quiet)]
    if not images:
        raise AutolabelError(f"{path} holds no frames OpenCV can read")
    shapes = {image.shape for image in images}
    if len(shapes) > 1:
        raise AutolabelError(f"the frames of {path} differ in size ({sorted(shapes)}): a capture is one camera's frames")
    return Capture(frames=np.stack(images), name=path.stem if path.is_file() else path.name, source=str(source),
                   kind="images" if path.is_dir() else "video")


@dataclass
class AutoLabels:
    """The recipe's labels of a capture: one static truth for all its frames.

    Attributes:
        ids: (M,) int64 corner IDs found in the average, ascending.
        corners: (C, 2) float32 their positions (OpenCV pixels), NaN for IDs not found.
        visible: (C,) bool, True for the IDs found.
        K: (3, 3) float64; dist: (D,) float64 distortion the pose was estimated with.
        rvec, tvec: (3,) float64 board -> camera pose of the average's corners.
        reprojection_error: the pose's eps_re on the average (px).
        motion_px: largest displacement of the board over the averaged frames (px), NaN if not checked.
        checked_frames: averaged frames in which OpenCV found corners to measure motion with.
        average: frames averaged; frames: frames in the capture.
        sequence, source: the capture's name and input path.
    """

    ids: np.ndarray
    corners: np.ndarray
    visible: np.ndarray
    K: np.ndarray
    dist: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    reprojection_error: float
    motion_px: float
    checked_frames: int
    average: int
    frames: int
    sequence: str = ""
    source: str = ""

    def describe(self) -> str:
        motion = ("not checked" if math.isnan(self.motion_px) else
                  f"board still to {self.motion_px:.2f} px over {self.checked_frames} of them")
        return (f"{len(self.ids)} corners from the mean of frames 0-{self.average - 1} ({motion}); "
                f"pose eps_re {self.reprojection_error:.3f} px")


def average_frames(frames: np.ndarray) -> np.ndarray:
    """(H, W) float64 mean of (N, H, W) uint8 frames."""
    return frames.astype(np.float64).mean(axis=0)


def board_motion(detections: list[Detection], reference: dict[int, np.ndarray]) -> tuple[float, int, int]:
    """How far the board moves over frames: (largest displacement px, its frame, frames checked).

    ``detections``: OpenCV's on each frame. A frame's displacement is the median over its corners
    of the distance from the ``reference`` position of the same ID (ID -> (2,) px); frames with
    none of the reference IDs are not checked. (NaN, -1, 0) when no frame could be checked."""
    worst, worst_frame, checked = -1.0, -1, 0
    for i, detection in enumerate(detections):
        distances = [float(np.linalg.norm(c - reference[int(j)])) for j, c in zip(detection.ids, detection.corners)
                     if int(j) in reference]
        if not distances:
            continue
        checked += 1
        if np.median(distances) > worst:
            worst, worst_frame = float(np.median(distances)), i
    return (float("nan"), -1, 0) if checked == 0 else (worst, worst_frame, checked)


def median_positions(detections: list[Detection]) -> dict[int, np.ndarray]:
    """ID -> (2,) median position over the detections that hold it."""
    seen: dict[int, list[np.ndarray]] = {}
    for detection in detections:
        for i, c in zip(detection.ids, detection.corners):
            seen.setdefault(int(i), []).append(c)
    return {i: np.median(np.stack(cs), axis=0) for i, cs in seen.items()}


def autolabel(frames: np.ndarray, K: np.ndarray, dist: np.ndarray | None = None, board: BoardSpec | None = None, *,
              average: int = AVERAGE_FRAMES, max_motion: float = MAX_MOTION_PX, sequence: str = "",
              source: str = "") -> AutoLabels:
    """The paper's recipe on (N, H, W) uint8 frames of a static board; raises `AutolabelError` when
    it cannot label them truthfully (module docstring). ``max_motion`` = inf skips the motion check."""
    board = board or BoardSpec()
    frames = np.asarray(frames)
    if frames.ndim != 3 or frames.dtype != np.uint8:
        raise AutolabelError(f"frames must be (N, H, W) uint8 grayscale, got {frames.dtype} {frames.shape}")
    if average < 1:
        raise AutolabelError(f"average must be >= 1 frame, got {average}")
    label = sequence or "the capture"
    if len(frames) < average:
        raise AutolabelError(f"{label} has {len(frames)} frames; the recipe averages the first {average}: "
                             f"capture at least {average} frames of the still board (or lower --average)")
    detector = OpenCVDetector(board, refine="subpix")
    mean = np.clip(np.round(average_frames(frames[:average])), 0, 255).astype(np.uint8)
    found = detector.detect(mean)
    not_found = AutolabelError(
        f"{label}: OpenCV finds {len(found)} board corner(s) in the average of the first {average} frames "
        f"(at least {MIN_CORNERS} needed): is the board in view, well lit, and is --board right ({board})?")

    motion, checked = float("nan"), 0
    if math.isfinite(max_motion):
        detections = [detector.detect(frame) for frame in frames[:average]]
        # Motion blurs the average, which may then show no board: compare the frames with their own median.
        reference = {int(i): c for i, c in zip(found.ids, found.corners)} or median_positions(detections)
        motion, worst_frame, checked = board_motion(detections, reference)
        if checked == 0:
            if len(found) < MIN_CORNERS:
                raise not_found
            raise AutolabelError(
                f"{label}: OpenCV finds the board in the average but in none of the first {average} frames alone, so "
                f"nothing shows that it stands still. Film it in better light, or pass --max-motion inf to skip the check")
        if motion > max_motion:
            raise AutolabelError(
                f"{label}: the board moves by {motion:.2f} px (frame {worst_frame}, median over its corners) during "
                f"the first {average} frames, more than --max-motion {max_motion:g} px: the recipe needs a still "
                f"board and camera. Recapture with the camera fixed (or raise --max-motion)")
    if len(found) < MIN_CORNERS:
        raise not_found
    dist = np.zeros(5) if dist is None else np.asarray(dist, np.float64).ravel()
    pose = estimate_pose(found, K, dist, board=board)
    if pose is None:
        raise AutolabelError(f"{label}: no board pose from the {len(found)} corners found in the average "
                             f"(they lie on a line, or disagree with the camera's K): check --camera and --board")
    corners = np.full((board.num_corners, 2), np.nan, np.float32)
    corners[found.ids] = found.corners
    visible = np.zeros(board.num_corners, bool)
    visible[found.ids] = True
    return AutoLabels(ids=found.ids, corners=corners, visible=visible, K=np.asarray(K, np.float64), dist=dist,
                      rvec=pose.rvec, tvec=pose.tvec, reprojection_error=pose.reprojection_error, motion_px=motion,
                      checked_frames=checked, average=average, frames=len(frames), sequence=sequence, source=source)


def label_capture(capture: Capture, labels: AutoLabels) -> list[FrameLabels]:
    """The capture's frames with the auto-labels, as shard frames (docs/conventions.md schema).

    Meta: ``sequence``, ``sequence_frame``, ``has_board`` (True), ``autolabel_source`` (input
    path), ``autolabel_corners``, ``autolabel_reprojection_error``, ``autolabel_motion_px``,
    ``visible_count``, ``dist_k1``.. (the distortion the pose used); a shard input's own meta
    (lux, blur_px, condition ...) is carried over."""
    dist = np.zeros(max(5, labels.dist.size))
    dist[:labels.dist.size] = labels.dist
    records = []
    for k in range(len(capture.frames)):
        carried = dict(capture.meta[k]) if capture.meta else {}
        records.append({
            **carried, "sequence": capture.name, "sequence_frame": k, "has_board": True,
            "autolabel_source": capture.source, "autolabel_corners": len(labels.ids),
            "autolabel_reprojection_error": float(labels.reprojection_error),
            "autolabel_motion_px": float(labels.motion_px), "visible_count": int(labels.visible.sum()),
            **{f"dist_{DIST_NAMES[i] if i < len(DIST_NAMES) else i}": float(v) for i, v in enumerate(dist)},
        })
    return [FrameLabels(image=capture.frames[k], corners=labels.corners.copy(), visible=labels.visible.copy(),
                        K=labels.K.astype(np.float32), rvec=labels.rvec.astype(np.float32),
                        tvec=labels.tvec.astype(np.float32), meta=records[k]) for k in range(len(capture.frames))]


@dataclass
class TruthComparison:
    """Auto-labels against render truth, frame by frame.

    Attributes:
        errors: (F, C) px distance of each auto-labelled corner from the truth; NaN where not
            compared (ID not auto-labelled, or not visible in the truth).
        rotation_deg: (F,) angle between the auto-labelled and the true board rotation.
        translation_m: (F,) distance between the translations; translation_rel: / true distance.
        conditions: (F,) the truth's ``meta/condition`` per frame ("" when absent).
    """

    errors: np.ndarray
    rotation_deg: np.ndarray
    translation_m: np.ndarray
    translation_rel: np.ndarray
    conditions: np.ndarray = field(default_factory=lambda: np.zeros(0, str))

    def summary(self, frames: np.ndarray | None = None) -> dict:
        """median_px, p95_px, max_px, corners, frames; rotation_deg and translation_mm (median, max),
        translation_rel_max — over all frames or the boolean/index selection ``frames``."""
        selection = slice(None) if frames is None else frames
        errors = self.errors[selection]
        values = errors[np.isfinite(errors)]
        rotation, translation = self.rotation_deg[selection], self.translation_m[selection]

        def stat(fn, array):
            return float(fn(array)) if array.size else float("nan")

        return {"median_px": stat(np.median, values), "p95_px": stat(lambda a: np.percentile(a, 95), values),
                "max_px": stat(np.max, values), "corners": int(values.size), "frames": int(errors.shape[0]),
                "rotation_deg_median": stat(np.median, rotation), "rotation_deg_max": stat(np.max, rotation),
                "translation_mm_median": stat(np.median, translation) * 1e3,
                "translation_mm_max": stat(np.max, translation) * 1e3,
                "translation_rel_max": stat(np.max, self.translation_rel[selection])}

    def describe(self) -> str:
        s = self.summary()
        return (f"against the render truth: corners median {s['median_px']:.3f} px, p95 {s['p95_px']:.3f} px, "
                f"max {s['max_px']:.3f} px over {s['corners']} corners of {s['frames']} frames; pose: rotation "
                f"{s['rotation_deg_median']:.3f} deg median / {s['rotation_deg_max']:.3f} max, translation "
                f"{s['translation_mm_median']:.2f} mm median / {s['translation_mm_max']:.2f} mm max "
                f"({100 * s['translation_rel_max']:.2f} % of the distance)")


def compare_to_truth(autolabels: AutoLabels | str | Path, truth_shard: str | Path) -> TruthComparison:
    """Per-corner and pose error of auto-labels against a shard of renders.

    ``autolabels``: an `AutoLabels` (the same labels for every frame) or an auto-label shard
    written by this module (its per-frame labels). ``truth_shard``: the render shard the capture
    came from (same frames, same order)."""
    truth = ShardReader(truth_shard)
    labels_reader = None if isinstance(autolabels, AutoLabels) else ShardReader(autolabels)
    try:
        count = len(truth) if labels_reader is None else len(labels_reader)
        if count != len(truth):
            raise AutolabelError(f"{autolabels} has {count} frames but the truth {truth_shard} has {len(truth)}: "
                                 f"compare auto-labels with the shard they were made from")
        errors = np.full((count, truth.board.num_corners), np.nan)
        rotation, translation, relative = np.zeros(count), np.zeros(count), np.zeros(count)
        conditions = []
        for k in range(count):
            frame = truth[k]
            if labels_reader is None:
                corners, visible, rvec, tvec = autolabels.corners, autolabels.visible, autolabels.rvec, autolabels.tvec
            else:
                labelled = labels_reader[k]
                corners, visible, rvec, tvec = labelled.corners, labelled.visible, labelled.rvec, labelled.tvec
            compared = np.asarray(visible, bool) & frame.visible
            errors[k, compared] = np.linalg.norm(np.asarray(corners, np.float64)[compared] - frame.corners[compared], axis=1)
            rotation[k] = rotation_error_deg(rvec, frame.rvec)
            translation[k] = float(np.linalg.norm(np.asarray(tvec, np.float64) - frame.tvec))
            relative[k] = translation[k] / max(float(np.linalg.norm(frame.tvec)), 1e-9)
            conditions.append(str(frame.meta.get("condition", "")))
    finally:
        truth.close()
        if labels_reader is not None:
            labels_reader.close()
    return TruthComparison(errors=errors, rotation_deg=rotation, translation_m=translation, translation_rel=relative,
                           conditions=np.array(conditions))


def autolabel_capture(source: str | Path, camera: str | Path | None = None, board: BoardSpec | None = None, *,
                      average: int = AVERAGE_FRAMES, max_motion: float = MAX_MOTION_PX,
                      quiet: bool = True) -> tuple[Capture, AutoLabels]:
    """Read ``source`` and auto-label it. K and distortion come from ``camera`` (an OpenCV YAML file,
    scaled to the frames' size) or, for a shard, from the shard when no camera is given."""
    capture = read_capture(source, quiet=quiet)
    height, width = capture.frames.shape[1:]
    if camera is not None:
        intrinsics = read_camera(camera).for_image_size(width, height)
        K, dist = intrinsics.K, intrinsics.dist
    elif capture.K is not None:
        K, dist = capture.K, np.zeros(5)
    else:
        raise AutolabelError(f"{source} is a {capture.kind}: give its camera's intrinsics with --camera cam.yaml "
                             f"(OpenCV calibration YAML); only a shard carries its own K")
    if capture.kind == "shard" and board is None:
        board = ShardReader(source).board
    labels = autolabel(capture.frames, K, dist, board, average=average, max_motion=max_motion, sequence=capture.name,
                       source=capture.source)
    return capture, labels


def autolabel_sequence_errors(directory: str | Path, board: BoardSpec | None = None, *, average: int = AVERAGE_FRAMES,
                              max_motion: float = MAX_MOTION_PX, quiet: bool = False) -> dict:
    """The recipe run on every rendered sequence in ``directory`` and compared with the render truth.

    Returns a JSON-able dict: the pooled ``median_px``, ``p95_px``, ``max_px``, ``corners``,
    ``sequences`` (labelled), pose errors (`TruthComparison.summary` keys) over all frames;
    ``still_camera``: the same over the lux and shadow sequences (where the recipe's premise
    holds in every frame; in a motion sequence the camera shakes after the averaged frames and
    the static labels are off by the shake); ``by_condition``; ``per_sequence``; and
    ``refused``: sequence -> the recipe's reason."""
    paths = list_shards(directory)
    comparisons, refused, per_sequence = [], {}, []
    for path in tqdm(paths, desc="autolabel", unit="sequence", disable=quiet):
        reader = ShardReader(path)
        if board is not None and reader.board != board:
            raise AutolabelError(f"{path} holds frames of {reader.board}, not of {board}")
        reader.close()
        try:
            capture, labels = autolabel_capture(path, None, board, average=average, max_motion=max_motion)
        except AutolabelError as error:
            refused[path.name] = str(error)
            continue
        comparison = compare_to_truth(labels, path)
        comparisons.append(comparison)
        per_sequence.append({"sequence": capture.name, "shard": path.name, **comparison.summary()})
    if not comparisons:
        return {"sequences": 0, "corners": 0, "refused": refused, "per_sequence": []}
    pooled = TruthComparison(errors=np.concatenate([c.errors for c in comparisons]),
                             rotation_deg=np.concatenate([c.rotation_deg for c in comparisons]),
                             translation_m=np.concatenate([c.translation_m for c in comparisons]),
                             translation_rel=np.concatenate([c.translation_rel for c in comparisons]),
                             conditions=np.concatenate([c.conditions for c in comparisons]))
    by_condition = {str(c): pooled.summary(pooled.conditions == c) for c in dict.fromkeys(pooled.conditions.tolist())}
    return {**pooled.summary(), "sequences": len(comparisons),
            "still_camera": pooled.summary(np.isin(pooled.conditions, ["lux", "shadow"])),
            "by_condition": by_condition, "per_sequence": per_sequence, "refused": refused}


def _next_index(out: Path) -> int:
    shards = list_shards(out) if out.is_dir() else []
    return 1 + max((int(p.stem.split("-")[1]) for p in shards), default=-1)


def _check_out(out: Path, index: int, capture: Capture) -> None:
    """Refuse to overwrite a shard, to label the same sequence twice into one folder, or to mix
    auto-labels into the folder of the renders they were made from."""
    name = capture.name
    if capture.kind == "shard" and out.resolve() == Path(capture.source).parent.resolve():
        raise AutolabelError(f"--out {out} is the folder of the input shard: auto-labels would mix with the render "
                             f"truth there; choose another --out")
    if not out.is_dir():
        return
    for path in list_shards(out):
        reader = ShardReader(path)
        try:
            other = str(reader[0].meta.get("sequence", "")) if len(reader) else ""
        finally:
            reader.close()
        if path.name == f"shard-{index:05d}.h5":
            raise AutolabelError(f"{out} already holds {path.name} (sequence {other!r}); choose another --index or "
                                 f"--out; nothing was written")
        if other == name:
            raise AutolabelError(f"{out} already holds sequence {name!r} as {path.name}; remove that file to label it "
                                 f"again, or choose another --out; nothing was written")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m evaluate.paper.autolabel", formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description="Label a capture of a static ChArUco board the paper's way: OpenCV + cornerSubPix on the average "
                    "of its first frames is the truth of every frame. Writes one shard (schema: docs/conventions.md).")
    parser.add_argument("video", metavar="VIDEO", help="video file, folder of images (sorted by name), or shard-*.h5")
    parser.add_argument("--camera", default=None,
                        help="OpenCV calibration YAML (camera_matrix, distortion_coefficients, image_width/height); "
                             "optional for a shard, which carries K")
    parser.add_argument("--board", default=None, help="BoardSpec .json/.yaml (default: a shard's board, else the paper's "
                                                      "5x5 DICT_5X5_50 board)")
    parser.add_argument("--out", default="data/captures", help="folder of auto-labelled shards (evaluate.report --captures)")
    parser.add_argument("--index", type=int, default=None,
                        help="shard index to write (default: a shard input's own index, else the next free one)")
    parser.add_argument("--average", type=int, default=AVERAGE_FRAMES, help="first frames averaged for the truth")
    parser.add_argument("--max-motion", type=float, default=MAX_MOTION_PX,
                        help="refuse when the board moves more than this (px) during the averaged frames; inf: no check")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    problems = []
    if args.average < 1:
        problems.append(f"--average must be >= 1, got {args.average}")
    if not args.max_motion > 0:
        problems.append(f"--max-motion must be > 0 px (inf: no check), got {args.max_motion}")
    if args.index is not None and args.index < 0:
        problems.append(f"--index must be >= 0, got {args.index}")
    if problems:
        parser.error("; ".join(problems))

    def body() -> None:
        board = BoardSpec.load(args.board) if args.board else None
        capture, labels = autolabel_capture(args.video, args.camera, board, average=args.average,
                                            max_motion=args.max_motion, quiet=args.quiet)
        board = board or (ShardReader(args.video).board if capture.kind == "shard" else BoardSpec())
        out = Path(args.out)
        index = args.index if args.index is not None else (
            capture.shard_index if capture.shard_index is not None else _next_index(out))
        _check_out(out, index, capture)
        output_folder(out)
        generator = {"package": "deepcharuco", "version": deepcharuco.__version__, "command": "evaluate.paper.autolabel",
                     "args": {"source": capture.source, "average": args.average, "max_motion": args.max_motion,
                              "camera": args.camera, "board": board.to_dict()},
                     "autolabel": {"ids": labels.ids.tolist(), "reprojection_error": labels.reprojection_error,
                                   "motion_px": None if math.isnan(labels.motion_px) else labels.motion_px,
                                   "checked_frames": labels.checked_frames}}
        path = write_shard(out, index, label_capture(capture, labels), board, generator)
        print(f"{capture.name}: {labels.describe()}; wrote {path} ({len(capture.frames)} frames)")
        if capture.has_truth:
            print(f"{capture.name}: {compare_to_truth(labels, args.video).describe()}")

    return run_command(body)


if __name__ == "__main__":
    sys.exit(main())
