"""The real-captures section: every set through every detector, the gallery of frames where they disagree
(JPEG, drawn on the real image with `deepcharuco.cli.draw`), and the report's table rows."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import cv2
import numpy as np

from deepcharuco.cli.draw import draw_detection
from deepcharuco.core.detection import Detection
from evaluate.captures.measure import REFERENCE, GalleryFrame, build_detectors, evaluate_capture_set
from evaluate.captures.reader import CaptureError, open_capture_set

SAMPLE = Path(__file__).resolve().parents[1] / "captures_sample"  # shipped in the repository, attributed
# Every 4th frame of a video (its frames_review.csv rates the even ones): the four published sets then take
# minutes, not the better part of an hour, with the deep detector at ~2 s a 1280x720 frame on 2 cores.
DEFAULT_STEP = 4
DEFAULT_GALLERY = 3  # frames a set
JPEG_QUALITY = 85
LABELS = {"opencv": "OpenCV + cornerSubPix", "deep": "deep (ChArUcoNet + RefineNet + pattern fit)",
          "hybrid": "hybrid (OpenCV, else the networks)"}
SHORT = {"opencv": "OpenCV", "deep": "deep", "hybrid": "hybrid"}  # in the gallery's captions


def sample_folders() -> list[Path]:
    """The shipped sample's capture sets (folders with a board.yaml), sorted."""
    return sorted(p.parent for p in SAMPLE.glob("*/board.yaml"))


def evaluate_captures(folders: list[str | Path], weights: str | None = None, refine_weights: str | None = None,
                      device: str = "cpu", step: int = DEFAULT_STEP, limit: int | None = None,
                      gallery: int = DEFAULT_GALLERY, quiet: bool = True, network: str = "lite"
                      ) -> tuple[dict, dict[str, bytes]]:
    """Every capture folder through OpenCV and the deep detector -> (results, JPEG gallery images by name).
    All folders are opened and checked before any is evaluated, so a bad one fails fast; files among them
    (a shell glob's README.md) are skipped, named on stderr and in ``results["skipped"]``."""
    started = time.perf_counter()
    skipped = [str(f) for f in folders if Path(f).is_file()]
    for name in skipped:
        print(f"skipping {name}: a file, not a capture folder", file=sys.stderr)
    sets = [open_capture_set(folder, step=step, limit=limit) for folder in folders if str(folder) not in skipped]
    if not sets:
        raise CaptureError(f"no capture folders among {', '.join(map(str, folders))}: give folders holding "
                           f"board.yaml and the photos or videos of that board")
    results: dict = {"step": step, "limit": limit, "sets": [], "gallery": [], "skipped": skipped}
    pictures: dict[str, bytes] = {}
    for captures in sets:
        detectors = build_detectors(captures.board, weights, refine_weights, device, network)
        result, kept = evaluate_capture_set(captures, detectors, step, limit, gallery, quiet)
        results["sets"].append(result)
        for entry in kept:
            name = f"capture_{len(results['gallery']):02d}"
            pictures[name] = gallery_image(entry, result["camera"])
            results["gallery"].append({"figure": name, "set": captures.name, "frame": entry.name,
                                       "disagreement": round(entry.score, 3)})
    results["detectors"] = {n: LABELS.get(n, n) for s in results["sets"] for n in s["detectors"]}
    results["seconds"] = round(time.perf_counter() - started, 1)
    return results, pictures


def _panel(image: np.ndarray, detection: Detection, caption: str) -> np.ndarray:
    """The (reduced) frame contrast-stretched for viewing (dark frames too), the detection drawn on it, and a
    caption bar under it."""
    low, high = np.percentile(image, (1, 99.5))
    stretched = np.clip((image.astype(np.float32) - low) * 255.0 / max(high - low, 1.0), 0, 255).astype(np.uint8)
    canvas = draw_detection(stretched, detection)
    bar = np.zeros((22, canvas.shape[1], 3), np.uint8)
    cv2.putText(bar, caption, (5, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 255), 1, cv2.LINE_AA)
    return np.vstack([canvas, bar])


def _caption(entry: GalleryFrame, name: str, camera: bool) -> str:
    m = entry.measure
    text = f"{SHORT.get(name, name)}: {m.found[name]}"
    if m.verified[name]:
        text += f", pose eps_re {m.eps_re[name]:.2f}px" if camera and m.eps_re[name] is not None else ", verified"
    if name != REFERENCE and m.reference:
        text += f", {m.agree[name]}/{m.reference} agree" + (f", {m.wrong[name]} WRONG IDs" if m.wrong[name] else "")
    return text


def gallery_image(entry: GalleryFrame, camera: bool) -> bytes:
    """One frame through every detector, side by side (OpenCV first), as JPEG bytes; the frame's name on top."""
    names = [REFERENCE] + [n for n in entry.detections if n != REFERENCE]
    panels = [_panel(entry.image, entry.detections[n], _caption(entry, n, camera)) for n in names]
    gap = np.full((panels[0].shape[0], 6, 3), 255, np.uint8)
    row = np.hstack([part for panel in panels for part in (panel, gap)][:-1])
    title = np.full((20, row.shape[1], 3), 255, np.uint8)
    review = f" (by eye: board visible {entry.measure.review})" if entry.measure.review else ""
    cv2.putText(title, f"{entry.name}{review}", (5, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    ok, encoded = cv2.imencode(".jpg", np.vstack([title, row]), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return encoded.tobytes()


def _value(value, digits: int = 2, percent: bool = False) -> str:
    if value is None:
        return "-"
    return f"{100 * value:.0f}%" if percent else f"{value:.{digits}f}"


def capture_sections(real: dict) -> list[tuple[str, str, list[list[str]] | None, list[str]]]:
    """(title, text, table rows, figure names) of the report's "Real captures" sections (documents.sections)."""
    truth = any(s["truth"] != "none" for s in real["sets"])
    review = any(s["review"] for s in real["sets"])
    header = ["set", "detector", "frames", "corners", "found (>= 4)", "verified", "eps_re px", "OpenCV >= 6",
              "acc vs OpenCV", "px vs OpenCV", "wrong IDs", "only this / only OpenCV", "ms/frame"]
    header += ["OpenCV missed, board seen by eye: found", "no board: found"] if review else []
    header += ["truth: corner acc / pose acc / wrong poses"] if truth else []
    rows = [header]
    for s in real["sets"]:
        for name, d in s["detectors"].items():
            cells = [s["set"], real["detectors"].get(name, name), str(d["frames"]), str(d["corners"]), str(d["found"]),
                     str(d["verified"]),
                     _value(d["mean_eps_re"]), str(d["reference_frames"]),
                     "-" if name == REFERENCE else _value(d["accuracy_vs_opencv"]),
                     "-" if name == REFERENCE else _value(d["median_px_vs_opencv"]),
                     "-" if name == REFERENCE else f"{d['wrong_ids']} in {d['wrong_id_frames']} frames",
                     "-" if name == REFERENCE else f"{d['only_this']} / {d['only_opencv']}",
                     _value(d["ms_per_frame"], 0)]
            if review:
                verdicts = d.get("review", {})
                seen = [verdicts.get(v, [0, 0]) for v in ("yes", "partial")]
                cells += [f"{sum(a for a, _ in seen)} / {sum(b for _, b in seen)}" if "review" in d else "-",
                          "{} / {}".format(*verdicts["no"]) if "no" in verdicts else "-"]
            if truth:
                t = d.get("truth")
                cells.append("-" if t is None else f"{_value(t['corner_accuracy'])} / "
                             f"{_value(t.get('pose_accuracy'), percent=True)} / {t.get('confidently_wrong', '-')}")
            rows.append(cells)
    step = f"every {real['step']}th frame of each video" if real["step"] > 1 else "every frame of each video"
    text = (f"Photos and videos of printed boards from real cameras, {step}, every photo. corners: all the corners "
            "found; found: frames with >= 4 corners; verified: >= 6 corners that fit one view of the board (RANSAC homography, 3 px) or, with a "
            "camera file, a PnP pose (6+ inliers, lens distortion included) with eps_re < 3 px, whose mean is shown; "
            "acc vs OpenCV: the paper's accuracy with OpenCV's corners as the truth (same ID within 3 px), over "
            "the frames where OpenCV finds >= 6 corners, and the median distance of those corners; wrong IDs: "
            "corners more than half a square from OpenCV's corner of the same ID; only: frames one of the two "
            "finds (>= 4 corners) and the other does not.")
    if review:
        text += (" A by-eye review (frames_review.csv) rates the frames OpenCV missed: found = frames with >= 4 "
                 "corners among those with the board visible or partly visible, and among those with no board.")
    text += " Truth: " + " ".join(f"{s['set']}: {s['truth']} ({'; '.join(s['truth_notes'])})." for s in real["sets"])
    text += f" {real['seconds']:.0f} s in all."
    out = [("Real captures", text, rows, [])]
    if real["gallery"]:
        out.append(("Real captures: where the detectors disagree",
                    "The frames where the detectors disagree most (one verifies a view the other does not, wrong "
                    "IDs, corners OpenCV found that the other missed), OpenCV on the left. Green circles and yellow "
                    "numbers: the corners each found, on the real frame (reduced, contrast-stretched for viewing).",
                    None, [g["figure"] for g in real["gallery"]]))
    return out


def report_folders(folders: list[str] | None, disabled: bool = False) -> tuple[str | None, list[Path]]:
    """``evaluate.report``'s ``--captures`` -> (the folder of auto-labelled shards (python -m evaluate.paper.autolabel),
    evaluated as the paper's per-video table, or None; the capture-set folders). Without ``--captures``: the
    shipped sample; with ``--no-captures`` (``disabled``): none."""
    if disabled:
        if folders:
            raise CaptureError("--captures and --no-captures contradict each other: give one of them")
        return None, []
    if folders is None:
        return None, sample_folders()
    shards = [f for f in folders if Path(f).is_dir() and any(Path(f).glob("shard-*.h5"))]
    if len(shards) > 1:
        raise CaptureError(f"--captures names {len(shards)} folders of auto-labelled shards ({', '.join(shards)}): "
                           f"give one (python -m evaluate.paper.autolabel --out writes them all to one folder)")
    return (shards[0] if shards else None), [Path(f) for f in folders if f not in shards]
