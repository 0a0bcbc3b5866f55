"""The paper's evaluation: its protocols, its test sets and the experiments, tables and figures of the report.

- `protocols`: the paper's protocols (synthetic blur and darkness, pose accuracy, eps_re), usable with any detector;
- `data`: test frames from shard folders; `sequences`: rendered twins of the paper's 26 evaluation videos
  (``python -m evaluate.paper.sequences``);
- `experiments`: the protocols run over the test sets for every detector; `figures`: the report's pictures;
- `unseen_boards`: the protocols re-run on boards the detector was never trained on; `false_positives`: what
  the detectors report on boards that are not the target and on photos without one;
- `autolabel`: the paper's auto-labelling of a video of a still board and camera
  (``python -m evaluate.paper.autolabel VIDEO --camera cam.yaml``), one source of `evaluate.captures`' truth;
- `readme_figure`: the README's picture.

The bottom of `evaluate/`: it imports no other part of it (`evaluate/__init__.py` gives the order).
"""
