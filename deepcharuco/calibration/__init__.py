"""Calibration: one camera's intrinsics from its views of the board (view selection, the solve, the model's
terms, per-corner weights, deviations) and a rig's cameras together (bundle adjustment), with their files and
HTML reports.

Imports `deepcharuco.core`, `boards` and `geometry`: never the detectors (the command line feeds it their
detections). The names here are loaded on first use.
"""

from typing import TYPE_CHECKING

from deepcharuco.core.lazy import lazy_exports

_WHERE = {
    "calibrate": "intrinsics", "CalibrationResult": "intrinsics", "CalibrationError": "views",
    "FrameDetection": "views", "SelectionOptions": "views",
    "calibrate_rig": "rig", "RigView": "rig_model", "RigResult": "rig_model", "RigError": "rig_model",
}
__all__ = list(_WHERE)
__getattr__, __dir__ = lazy_exports(__name__, _WHERE)

if TYPE_CHECKING:
    from deepcharuco.calibration.intrinsics import CalibrationResult, calibrate
    from deepcharuco.calibration.rig import calibrate_rig
    from deepcharuco.calibration.rig_model import RigError, RigResult, RigView
    from deepcharuco.calibration.views import CalibrationError, FrameDetection, SelectionOptions
