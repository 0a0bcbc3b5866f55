"""The card stage: MODEL_CARD.md from the plan, the stages' records and the evaluation stage's numbers."""

from __future__ import annotations

import json
import os
from pathlib import Path

from deepcharuco.core.files import write_atomic
from train.pipeline.evaluation import bundle_summary
from train.pipeline.plan import human
from train.pipeline.records import slug
from train.pipeline.stages import Pipeline


def write_card(pipeline: Pipeline) -> Path:
    """MODEL_CARD.md of a run whose stages ran: what the weights are, the command that makes them again, the
    stages as run (commands and times), the numbers measured by the evaluation stage and what was chosen on
    which data."""
    run, s = pipeline.run, pipeline.sizes
    records = {p.stem: json.loads(p.read_text()) for p in sorted((run / "stages").glob("*.json"))}
    bundle = records.get("bundle", {}).get("result") or bundle_summary(run / "detector.pt")
    results = json.loads((run / "eval" / "results.json").read_text())["boards"]
    target = pipeline.target
    lines = [f"# Model card: `{run / 'detector.pt'}` ({target.name})", ""]
    if target.heads == "points":
        trained = "ChArUcoNet's point head and RefineNet" if s.refinenet_steps else \
            "ChArUcoNet's point head (RefineNet: the initial weights', `--refinenet-steps 0`)"
        lines += [f"A family model: {trained} trained on renders of random "
                  f"{target.family} boards. Its ID head is untrained (recorded in the file: `heads: points`), so "
                  "`Detector(board=..., weights=...)` finds every board by its markers (geometry \"markers\"); without "
                  "`board=` it looks for the board stored with the weights by the same route.", ""]
    else:
        lines += [f"ChArUcoNet (point and ID heads) and RefineNet for one board, {target.board}.", ""]
    lines += ["## Make it again", "", "    " + pipeline.reproduce_command(), "",
              "Hardware: " + hardware() + ".", "", "## Stages as run", "",
              "| stage | size | time | command |", "|---|---|---|---|"]
    for stage in pipeline.stages():
        record = records.get(slug(stage.name), {})
        took = ("this stage" if not record else "array tasks" if record.get("seconds") is None
                else human(record["seconds"]))  # a render split over a cluster's array tasks has no one time
        lines.append(f"| {stage.name} | {stage.size} | {took} | "
                     f"`{record.get('command') or 'in-process'}` |")
    if pipeline.notes:
        lines += ["", "Fitted to the budget: " + "; ".join(pipeline.notes) + "."]
    lines += ["", "## How it scores (evaluation stage, this run)", "",
              "Boards below were never in the training renders" + (" (the family renders are random boards; these "
                                                                  "are fixed evaluation boards)" if target.family
                                                                  else " as sequences: the training renders are other "
                                                                       "scenes of the same board") + ". "
              f"Each board: {s.eval_sequences} of the paper's 26 sequences, {s.eval_frames} frames each; the synthetic "
              "protocol on its well-lit first frames. deep / OpenCV + cornerSubPix.", "",
              "| board | synthetic images | k = 0 | blur k = 10 | darkness k = 9 | pose acc. | confidently wrong | "
              "eps_re good light | fps 320x240 |", "|---|---|---|---|---|---|---|---|---|"]
    for name, result in results.items():
        deep, cv = result["summary"]["deep"], result["summary"]["opencv"]

        def pair(key: str, fmt: str) -> str:
            return " / ".join("n/a" if v[key] is None else format(v[key], fmt) for v in (deep, cv))
        lines.append(f"| {name} | {result['synthetic_images']} | {pair('k0', '.2f')} | {pair('blur10', '.2f')} | "
                     f"{pair('dark9', '.2f')} | {100 * deep['pose_accuracy']:.1f} % / {100 * cv['pose_accuracy']:.1f} % | "
                     f"{deep['confidently_wrong']} / {cv['confidently_wrong']} | {pair('mean_eps_re_good_light', '.3f')} | "
                     f"{result['fps_320x240']:.1f} |")
    threshold = bundle.get("threshold")
    lines += ["", "## What was chosen on what", "",
              f"- Score threshold {threshold if threshold is None else f'{threshold:.2f}'}: chosen by `train.bundle "
              "--threshold auto` on the validation shards of the training renders (every 10th shard, never trained "
              "on), decoded as `Detector` decodes" + (" (by markers, each frame's own board)" if target.heads == "points"
                                                      else " (board-geometry check on)") + ".",
              f"- `best.pt` of each network: the best validation score on those shards (ChArUcoNet "
              f"{'point F1' if target.heads == 'points' else 'corner accuracy'}: "
              f"{_metric(bundle['charuconet'], 'score')} at step {bundle['charuconet']['step']}; RefineNet mean error "
              f"{_metric(bundle['refinenet'], 'score')} px at step {bundle['refinenet']['step']}).",
              "- Stage sizes: " + ("fitted to the time budget from measured rates (above)" if pipeline.notes
                                   else "the full plan or as given") + "; learning rates and schedules are the "
              "pipeline's fixed recipe (README, Training), not tuned on this run.",
              "- The evaluation boards and sequences (seed 1000 + run seed) were not looked at while training; "
              "nothing was tuned on them.", ""]
    path = run / "MODEL_CARD.md"
    write_atomic(path, "\n".join(lines))
    return path


def _metric(part: dict, key: str) -> str:
    value = (part.get("metrics") or {}).get(key)
    return "n/a" if value is None else f"{value:.3f}"


def hardware() -> str:
    """What the stages ran on, for the model card: its timings compare only on the same CPU (`evaluate.speed.machine`)."""
    import torch

    from evaluate.speed.machine import cpu_description

    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU"
    return f"{os.cpu_count()}-core {cpu_description()}, {gpu}; torch {torch.__version__}"
