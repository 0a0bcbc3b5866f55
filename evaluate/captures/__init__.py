"""Real captures in the evaluation: folders of photos and videos of printed boards, judged per detector.

    from evaluate.captures import open_capture_set, evaluate_captures
    captures = open_capture_set("evaluate/captures_sample/opencv_tutorial")   # checked: CaptureError when unusable
    results, jpegs = evaluate_captures(["evaluate/captures_sample/opencv_tutorial"], step=4)

- `reader`: the folder layout, lazy frames (videos one frame at a time), refusals with the fix;
- `truth`: labels file, else the paper's auto-labelling of still videos, else none;
- `measure`: metrics that need no truth (verified views, agreement with OpenCV, wrong IDs, frames only one
  detector finds, ms per frame) and the paper's with truth;
- `present`: the gallery of frames where the detectors disagree and the report's "Real captures" section.

``python -m evaluate.captures DIR [DIR ...]`` runs them alone; ``python -m evaluate.report`` adds the section
(the shipped sample, ``evaluate/captures_sample``, unless ``--captures`` names other folders).
"""

from evaluate.captures.measure import build_detectors, evaluate_capture_set
from evaluate.captures.present import (
    DEFAULT_STEP, capture_sections, evaluate_captures, report_folders, sample_folders,
)
from evaluate.captures.reader import CaptureError, CaptureFrame, CaptureSet, open_capture_set

__all__ = ["CaptureError", "CaptureFrame", "CaptureSet", "DEFAULT_STEP", "build_detectors", "capture_sections",
           "evaluate_capture_set", "evaluate_captures", "open_capture_set", "report_folders", "sample_folders"]
