"""One command makes a model: ``python -m train.pipeline --family DICT_4X4 --out runs/4x4 [--budget 6h]``.

Plans and runs the stages that the README's Training section lists as separate commands:

    render     python -m datagen.render            frames of random boards of the family (or of --board)
    patches    python -m datagen.patches           24x24 corner patches for RefineNet
    charuconet python -m train.charuconet          one stage, or two from scratch (plain, then ID-weighted)
    refinenet  python -m train.refinenet
    bundle     python -m train.bundle              both networks + the score threshold chosen on validation frames
    eval-data  python -m evaluate.paper.sequences  the paper's sequences rendered with the evaluation board(s)
    evaluate   (in-process)                        the paper's protocols, deep vs OpenCV, on those sequences
    card       (in-process)                        MODEL_CARD.md with the numbers measured here

``--family F``: a family model, the point head (+ RefineNet) trained on random boards of the family
(``--heads points``); it finds any board of the family by its markers (`Detector` geometry
"markers"); its ID head is untrained and recorded as such. ``--board B.yaml``: the shipped (or
``--init``) model fine-tuned on renders of that one board, ID head included.

Every stage knows when it is done (``stages/NAME.json``); rerunning the same command after a kill,
Ctrl-C or a preemption skips finished stages and resumes the one that was running (renders by
shard, training from ``last.pt``). The plan (stage sizes) is fixed at the first run and kept in
``plan.json``, so a resumed run finishes the plan it started. ``--budget`` fits the sizes not given
explicitly to a time budget, from rates measured at the start (one render frame, a few training
steps) or recorded by earlier stages in the run folder (``rates.json``).

Modules, each importing only those above it: `records` (the run folder's JSON records), `plan` (what to make,
stage sizes, the budget), `rates` (rates recorded and probed), `checks` (whether a stage's outputs read back),
`evaluation` (the evaluate stage's protocols), `stages` (`Pipeline`: the plan of a folder and its stages'
commands), `card` (MODEL_CARD.md), `run` (running the stages), `cluster` (SLURM / Kubernetes scripts),
`command` (the options and ``main``).
"""

from train.pipeline.command import main

__all__ = ["main"]
