"""Command-line options generated from `TrainConfig`: every field is ``--field-name``."""

from __future__ import annotations

import argparse
from dataclasses import fields

from deepcharuco.cli.common import run_command
from deepcharuco.networks.checkpoint import HEADS
from train.loop import TrainConfig, pick_device, train

HELP = {
    "data": "folder of shards", "out": "run folder (last.pt, best.pt, log.csv)", "steps": "optimizer steps in all",
    "width": "network width: paper or lite; RefineNet also fast (a space-to-depth encoder, a third of lite's cost)",
    "val_every": "steps between validations",
    "val_batches": "validation batches per validation", "checkpoint_every": "steps between last.pt saves",
    "workers": "DataLoader worker processes", "device": "auto (CUDA, else MPS, else CPU), cpu, cuda, cuda:1, mps",
    "amp": "mixed precision on CUDA",
    "init": "start from these weights (checkpoint or bundle of the same network), with a fresh optimizer and schedule",
    "id_positive_weight": "ChArUcoNet only: weight of cells holding a corner in the ID cross-entropy (1 = the paper's plain mean)",
    "heads": "ChArUcoNet only: 'all' trains the point and ID heads on one board's renders; 'points' the point head "
             "alone (ID loss off) on renders of any boards, e.g. a marker family: the checkpoint records that its ID "
             "head is untrained, so Detector finds every board by its markers",
    "label_sigma": "RefineNet only: width of the Gaussian target in 1/8 px grid cells; 0 = the paper's one-hot cell",
    "teacher": "RefineNet only: distil from this RefineNet (a checkpoint or a bundle, e.g. deepcharuco/weights/"
               "detector.pt): its 4096-way softmax as a soft target beside the labels' ('' = labels alone)",
    "distill_weight": "RefineNet only, with --teacher: weight of the teacher's term (T^2 KL) beside the labels' term",
    "temperature": "RefineNet only, with --teacher: the softmax temperature of the teacher's term",
    "crop": "ChArUcoNet only: train on random WxH crops, e.g. 160x120 (multiples of 8); '' = whole frames",
    "shadow_edges": "ChArUcoNet only: share of training crops on which a cast shadow's edge passes within 2 px of a "
                    "visible corner (0 = the paper's augmentation)",
    "resume": "continue the run in --out exactly where it stopped (the folder may have been moved; log.csv is cut "
              "back to the checkpoint's step)",
}


def parse_config(prog: str, description: str, defaults: dict, argv: list[str] | None = None) -> TrainConfig:
    parser = argparse.ArgumentParser(prog=prog, description=description, formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    base = TrainConfig(**defaults)
    for field in fields(TrainConfig):
        flag = "--" + field.name.replace("_", "-")
        default = getattr(base, field.name)
        if isinstance(default, bool):
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=default, help=HELP.get(field.name, " "))
        elif field.name == "width":
            parser.add_argument(flag, choices=("paper", "lite", "fast"), default=default, help=HELP[field.name])
        elif field.name == "heads":
            parser.add_argument(flag, choices=HEADS, default=default, help=HELP[field.name])
        else:
            parser.add_argument(flag, type=type(default), default=default, help=HELP.get(field.name, " "))
    args = parser.parse_args(argv)
    config = TrainConfig(**vars(args))
    problems = [f"--{name.replace('_', '-')} must be >= {low}" for name, low in
                (("steps", 1), ("batch_size", 1), ("val_every", 1), ("checkpoint_every", 1), ("log_every", 1), ("workers", 0))
                if getattr(config, name) < low]
    if config.lr <= 0:
        problems.append("--lr must be > 0")
    if config.distill_weight < 0 or config.temperature <= 0:
        problems.append("--distill-weight must be >= 0 and --temperature > 0")
    if not 0.0 <= config.shadow_edges <= 1.0:
        problems.append("--shadow-edges is a share of the crops, from 0 to 1")
    if config.id_positive_weight <= 0:
        problems.append("--id-positive-weight must be > 0")
    if config.crop:
        try:
            parse_crop(config.crop)
        except ValueError as error:
            problems.append(str(error))
    if problems:
        parser.error("; ".join(problems))
    return config


def parse_crop(text: str) -> tuple[int, int] | None:
    """"160x120" -> (160, 120); "" -> None. Both sides positive multiples of 8 (the network's cell)."""
    if not text:
        return None
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.isdigit() for p in parts) or any(int(p) <= 0 or int(p) % 8 for p in parts):
        raise ValueError(f"--crop {text!r}: give WIDTHxHEIGHT in positive multiples of 8, e.g. 160x120")
    return int(parts[0]), int(parts[1])


def run_trainer(kind: str, task_class, doc: str, score_name: str, defaults: dict, argv: list[str] | None = None) -> int:
    """``python -m train.<kind>``: parse options, build the task, train. Exit code 0 when the run
    reached --steps; 128 + the signal's number when SIGINT/SIGTERM stopped it after saving last.pt
    (130 / 143, what a shell reports for a process the signal ended, so ``train && bundle`` stops);
    2 with a one-line message on bad input."""
    config = parse_config(f"python -m train.{kind}", doc.splitlines()[0], defaults, argv)

    def body() -> int:
        pick_device(config.device)  # a bad --device is reported before the data is read
        result = train(task_class(config), config, kind)
        if result["signal"] is not None:
            return 128 + result["signal"]
        print(f"step {result['step']}: best validation {score_name} {result['best']}")
        return 0

    return run_command(body)
