"""Deep ChArUco against OpenCV: the paper's protocols and report, real captures, timing, calibration and rigs.

Subpackages, each importing only from those before it (tests/test_layers.py checks it):

- `evaluate.paper`: the paper's protocols, test sets (rendered, auto-labelled), experiments and figures (the
  bottom: imports no other part of `evaluate`);
- `evaluate.captures`: real photos and videos of printed boards, judged per detector;
- `evaluate.speed`: the machine a timing was taken on and the realistic frames that timings and scores use;
- `evaluate.calibration`: one camera's and a rig's calibration against truth, and sub-pixel corner precision;
- `evaluate.report` and `evaluate.documents` (the top): ``python -m evaluate.report`` runs every section and
  writes report.md, report.html and results.json.
"""
