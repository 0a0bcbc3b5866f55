"""What the stages left, checked: a stage is done when it recorded that it finished and its outputs read back
complete (shards, checkpoints, files); damaged outputs are moved aside before a run, so that their stage makes
them again. ``run`` is the run folder, ``stage`` a `train.pipeline.stages.Stage`, ``frames`` the plan's
training frames (what a finished render stage must hold)."""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

from datagen.shards import ShardReader, list_shards, read_patch_shard
from train.pipeline.plan import Stage
from train.pipeline.records import read_json, slug


def marker(run: Path, stage: Stage) -> Path:
    """The record a finished stage leaves: ``run/stages/NAME.json``."""
    return run / "stages" / f"{slug(stage.name)}.json"


def finished(run: Path, stage: Stage) -> bool:
    """The stage recorded that it finished (a readable marker), or, for a trainer, its last.pt reached its
    steps (trained elsewhere, e.g. by the cluster job)."""
    if read_json(marker(run, stage)) is not None:
        return True
    return bool(stage.folder and stage.steps and checkpoint_step(stage.folder / "last.pt") >= stage.steps)


def is_done(run: Path, stage: Stage, frames: int) -> bool:
    """A stage is done when it finished and its outputs read back complete: a marker alone is not enough (a
    deleted shard, a cut-off checkpoint)."""
    return finished(run, stage) and not damaged_files(run, stage) and missing_output(run, stage, frames) is None


def outputs(run: Path, stage: Stage) -> tuple[str, Path]:
    """(kind, path) of what ``stage`` makes: "frames" / "patches" (a folder of shards), "checkpoints" (a
    trainer's folder), "checkpoint", "json" or "text" (one file)."""
    name = stage.name
    if name == "render":
        return "frames", run / "data" / "renders"
    if name == "patches":
        return "patches", run / "data" / "patches"
    if stage.folder is not None:
        return "checkpoints", stage.folder
    if name == "bundle":
        return "checkpoint", run / "detector.pt"
    if name.startswith("eval-data "):
        return "frames", run / "eval" / slug(name[len("eval-data "):])
    if name == "evaluate":
        return "json", run / "eval" / "results.json"
    return "text", run / "MODEL_CARD.md"


def damaged_files(run: Path, stage: Stage) -> list[tuple[Path, str]]:
    """(file, why) for each file of ``stage``'s outputs that exists but does not read back."""
    kind, path = outputs(run, stage)
    if kind in ("frames", "patches"):
        if not path.is_dir():
            return []
        read = ShardReader if kind == "frames" else read_patch_shard
        return [(shard, why) for shard in list_shards(path) if (why := unreadable(read, shard))]
    if kind == "checkpoints":
        return [(p, why) for p in (path / "last.pt", path / "best.pt") if p.is_file()
                and (why := unreadable(load_checkpoint, p))]
    if not path.is_file():
        return []
    why = unreadable(load_checkpoint, path) if kind == "checkpoint" else (
        None if kind == "text" or read_json(path) is not None else "not valid JSON (cut off?)")
    return [(path, why)] if why else []


def missing_output(run: Path, stage: Stage, frames: int) -> str | None:
    """What a finished ``stage`` should have made and has not (a deleted shard, a missing file), or None."""
    kind, path = outputs(run, stage)
    if kind == "frames":
        if not path.is_dir() or not list_shards(path):
            return f"{path} holds no shards"
        if stage.name == "render":
            found = sum(frames_in(p) for p in list_shards(path))
            if found < frames:
                return f"{path} holds {found} of the plan's {frames} frames"
        return None
    if kind == "patches":
        return None if path.is_dir() and list_shards(path) else f"{path} holds no patch shards"
    if kind == "checkpoints":
        missing = [p.name for p in (path / "last.pt", path / "best.pt") if not p.is_file()]
        if missing:
            return f"{path} has no {' or '.join(missing)}"
        step = checkpoint_step(path / "last.pt")
        return None if step >= stage.steps else f"{path / 'last.pt'} is at step {step} of {stage.steps}"
    if not path.is_file() or path.stat().st_size == 0:
        return f"{path} is missing or empty"
    return None


def repair(run: Path, stages: list[Stage], frames: int) -> None:
    """Before running: move each damaged output aside (``NAME.damaged``, kept for a look), and mark a stage
    whose outputs do not verify as not done, saying what is redone. A trainer whose last.pt is damaged
    resumes from its best.pt (a full checkpoint of an earlier step) where that reads, else starts again."""
    for stage in stages:
        damaged = damaged_files(run, stage)
        for path, why in damaged:
            aside = path.with_name(path.name + ".damaged")
            os.replace(path, aside)
            print(f"note: {path} is damaged ({why}): moved to {aside.name}; stage {stage.name} makes it again",
                  file=sys.stderr)
        if stage.folder is not None and any(p.name == "last.pt" for p, _ in damaged):
            best = stage.folder / "best.pt"
            if best.is_file():
                shutil.copyfile(best, stage.folder / "last.pt")
                print(f"note: stage {stage.name} resumes from {best} (step {checkpoint_step(best)}), its last "
                      f"good checkpoint", file=sys.stderr)
            else:
                print(f"note: stage {stage.name} has no good checkpoint left: it starts again", file=sys.stderr)
        record = marker(run, stage)
        if record.exists() and (read_json(record) is None or damaged or missing_output(run, stage, frames)):
            why = missing_output(run, stage, frames) or ("its record is damaged" if not damaged else "damaged outputs")
            record.unlink()
            print(f"note: stage {stage.name} is not done ({why}): it runs again", file=sys.stderr)


def checkpoint_step(path: Path) -> int:
    """The step a trainer's checkpoint reached; 0 without one or with one that does not read (`repair` says so)."""
    if not path.is_file():
        return 0
    try:
        return int(load_checkpoint(path)["training"]["step"])
    except Exception:  # noqa: BLE001 - any unreadable checkpoint: torch raises RuntimeError, EOFError, pickle errors
        return 0


def load_checkpoint(path: Path) -> dict:
    import torch

    state = torch.load(path, map_location="cpu", weights_only=False)
    if not isinstance(state, dict):
        raise ValueError("not a checkpoint of this project")
    return state


def unreadable(read, path: Path) -> str | None:
    """None when ``read(path)`` succeeds, else why it failed (one line)."""
    try:
        result = read(path)
        if hasattr(result, "close"):
            result.close()
    except Exception as error:  # noqa: BLE001 - a damaged file can fail any way its reader does
        first = (str(error).splitlines() or [type(error).__name__])[0]
        return first.split(". ")[0][:160]  # its first sentence: torch's go on with advice for another situation
    return None


def frames_in(shard: Path) -> int:
    """The frames a frame shard holds; 0 when it does not read (opened once)."""
    try:
        return len(ShardReader(shard))
    except Exception:  # noqa: BLE001 - a damaged shard fails as its reader does: `damaged_files` says how
        return 0
