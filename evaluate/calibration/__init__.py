"""Calibration measured against truth: one camera, a rig of cameras, and the corners both rest on.

- `calibration_sequences`: rendered calibration videos with a known distorted camera
  (``python -m evaluate.calibration.calibration_sequences``); `calibration_eval`: the report's calibration section;
- `rig_views` (drawn views through a rig, no renderer), `rig_renders` (Blender renders of the same rig) and
  `rig_eval` (``python -m evaluate.calibration.rig_eval``: the rig solved against its truth);
- `compare_cameras`: camera files side by side, where only calibrations exist to compare;
- `corner_precision`: sub-pixel corner error against exact truth, by condition, for every way the project places
  a corner (``--calibration``: what that error does to a calibration).
"""
