"""The report's pictures as PNG bytes: the paper's curves and the gallery of hard frames."""

from __future__ import annotations


import cv2
import numpy as np

from deepcharuco.calibration.html_page import image_format, png, pyplot
from deepcharuco.cli.draw import draw_detection
from evaluate.paper.experiments import LABELS
from evaluate.paper.protocols import POSE_THRESHOLD_PX, PoseScore, TestFrame

STYLE = {"deep": ("tab:blue", "-o"), "deep_subpix": ("tab:cyan", "--^"), "deep_norefine": ("tab:purple", ":s"),
         "deep_paper": ("tab:green", "-.d"), "deep_markers": ("tab:olive", "--v"),
         "opencv": ("tab:red", "-o"), "opencv_norefine": ("tab:orange", "--s")}
TRUTH_COLOUR = (60, 60, 255)  # BGR red


def figure_file_name(name: str, data: bytes) -> str:
    """The file a figure is written to beside a markdown page: ``name.jpg`` for JPEG bytes (the real-captures
    gallery), else ``name.png``; the report and ``python -m evaluate.captures`` name their files alike."""
    return f"{name}.{'jpg' if image_format(data) == 'jpeg' else 'png'}"


def synthetic_figure(synthetic: dict, effect: str) -> bytes:
    """Mean corner accuracy vs k for each detector: the paper's blur / darkness figures."""
    plt = pyplot()
    figure, axis = plt.subplots(figsize=(5.2, 3.4))
    levels = synthetic["levels"]
    for name, curve in synthetic[effect].items():
        colour, marker = STYLE.get(name, ("gray", "-o"))
        axis.plot(levels, [np.nan if v is None else v for v in curve["accuracy"]], marker, color=colour,
                  label=LABELS.get(name, name))
    axis.set_xticks(levels)
    axis.set_ylim(-0.03, 1.03)
    axis.set_xlabel("horizontal motion-blur kernel size k" if effect == "blur" else "darkness k (image x 0.6^k)")
    axis.set_ylabel("corner detection accuracy")
    axis.set_title(f"Synthetic {'motion blur' if effect == 'blur' else 'darkness'} test "
                   f"({len(synthetic['images'])} images)")
    axis.grid(alpha=0.3)
    axis.legend(loc="lower left", fontsize=8)
    return png(figure)


def threshold_figure(curves: dict, title: str) -> bytes:
    """Fraction of frames with eps_re below each threshold: the paper's pose-accuracy figure."""
    plt = pyplot()
    figure, axis = plt.subplots(figsize=(5.2, 3.4))
    thresholds = curves["thresholds_px"]
    for name, values in curves.items():
        if name == "thresholds_px":
            continue
        colour, marker = STYLE.get(name, ("gray", "-"))
        axis.plot(thresholds, values, marker[:-1], color=colour, label=LABELS.get(name, name))  # the line, no markers
    axis.axvline(POSE_THRESHOLD_PX, color="gray", lw=0.8, ls=":")
    axis.set_xlim(0, max(thresholds))
    axis.set_ylim(-0.02, 1.02)
    axis.set_xlabel("reprojection error threshold (px)")
    axis.set_ylabel("fraction of frames with a pose under it")
    axis.set_title(title)
    axis.grid(alpha=0.3)
    axis.legend(loc="lower right", fontsize=8)
    return png(figure)


def _panel(frame: TestFrame, score: PoseScore, label: str, scale: int) -> np.ndarray:
    """The frame (stretched so dark frames can be seen) with the truth (red dots) and a detection."""
    image = frame.image
    low, high = np.percentile(image, (1, 99.5))
    stretched = np.clip((image.astype(np.float32) - low) * 255.0 / max(high - low, 1.0), 0, 255).astype(np.uint8)
    canvas = draw_detection(stretched, score.detection)
    for x, y in frame.corners[frame.visible]:
        cv2.circle(canvas, (int(round(x * 16)), int(round(y * 16))), 16, TRUTH_COLOUR, -1, cv2.LINE_AA, shift=4)
    canvas = cv2.resize(canvas, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    eps = f"eps_re {score.eps_re:.2f}px" if score.has_pose else "no pose"
    text = f"{label}: acc {score.accuracy:.2f}, {eps}" + (", WRONG POSE" if score.confidently_wrong else "")
    cv2.rectangle(canvas, (0, canvas.shape[0] - 22), (canvas.shape[1], canvas.shape[0]), (0, 0, 0), -1)
    cv2.putText(canvas, text, (6, canvas.shape[0] - 7), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return canvas


def gallery_image(frame: TestFrame, panels: list[tuple[PoseScore, str]], scale: int = 2) -> bytes:
    """One frame through several detectors, side by side ((score, label) each). The image is contrast-stretched
    for viewing only."""
    gap = np.full((frame.image.shape[0] * scale, 6, 3), 255, np.uint8)
    row = [_panel(frame, score, label, scale) for score, label in panels]
    row = np.hstack([part for panel in row for part in (panel, gap)][:-1])
    ok, encoded = cv2.imencode(".png", row)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return encoded.tobytes()
