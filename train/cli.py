"""Command-line options generated from `TrainConfig`: every field is ``--field-name``."""

from __future__ import annotations

import argparse
from dataclasses import fields

from train.loop import TrainConfig

HELP = {
    "data": "folder of shards", "out": "run folder (last.pt, best.pt, log.csv)", "steps": "optimizer steps in all",
    "width": "network width: paper or lite", "val_every": "steps between validations",
    "val_batches": "validation batches per validation", "checkpoint_every": "steps between last.pt saves",
    "workers": "DataLoader worker processes", "device": "auto, cpu, cuda, cuda:1, mps",
    "amp": "mixed precision on CUDA", "resume": "continue the run in --out exactly where it stopped",
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
            parser.add_argument(flag, choices=("paper", "lite"), default=default, help=HELP[field.name])
        else:
            parser.add_argument(flag, type=type(default), default=default, help=HELP.get(field.name, " "))
    args = parser.parse_args(argv)
    config = TrainConfig(**vars(args))
    problems = [f"--{name.replace('_', '-')} must be >= {low}" for name, low in
                (("steps", 1), ("batch_size", 1), ("val_every", 1), ("checkpoint_every", 1), ("log_every", 1), ("workers", 0))
                if getattr(config, name) < low]
    if config.lr <= 0:
        problems.append("--lr must be > 0")
    if problems:
        parser.error("; ".join(problems))
    return config
