"""One command makes a model: ``python -m train.pipeline --family DICT_4X4 --out runs/4x4 [--budget 6h]``.

Plans and runs the stages that the README's Training section lists as separate commands:

    render     python -m datagen.render      frames of random boards of the family (or of --board)
    patches    python -m datagen.patches     24x24 corner patches for RefineNet
    charuconet python -m train.charuconet    one stage, or two from scratch (the shipped recipe's plain then ID-weighted)
    refinenet  python -m train.refinenet
    bundle     python -m train.bundle        both networks + the score threshold chosen on validation frames
    eval-data  python -m evaluate.paper.sequences  the paper's sequences rendered with the evaluation board(s)
    evaluate   (in-process)                  the paper's protocols, deep vs OpenCV, on those sequences
    card       (in-process)                  MODEL_CARD.md with the numbers measured here

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
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from datagen.family import FamilyError, parse_families
from datagen.shards import ShardReader, list_shards, read_patch_shard
from deepcharuco.board import MARKER_FAMILIES, BoardSpec, marker_family
from deepcharuco.cli import check_output_folder, output_folder, run_command
from deepcharuco.errors import DeepCharucoError
from deepcharuco.files import write_atomic

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "deepcharuco" / "weights" / "detector.pt"

# Evaluation sequences in the order a budget keeps them: the well-lit ones anchor the synthetic protocol,
# then the darkest, shadows and shake (what OpenCV fails on), then the rest.
SEQUENCE_PRIORITY = ("lux-700-a", "lux-400-b", "lux-1-a", "lux-0.3-b", "shadow-1", "motion-1", "lux-10-a",
                     "lux-100-b", "shadow-3", "motion-3", "lux-3-a", "lux-30-b", "lux-700-b", "lux-400-a",
                     "lux-100-a", "lux-50-a", "lux-50-b", "lux-30-a", "lux-10-b", "lux-5-a", "lux-5-b",
                     "lux-3-b", "lux-1-b", "lux-0.3-a", "shadow-2", "motion-2")
MIN_EVAL_SEQUENCES = 4
EVAL_RENDER_SHARE = 0.25  # an evaluation sequence frame's render cost / a training frame's, until measured

# Rates assumed when none was measured or recorded yet (this project's 2-core CPU, README / model card).
ASSUMED_RATES = {"render_s_per_frame": 0.5, "eval_render_s_per_frame": 0.5, "detect_s_per_image": 0.04,
                 "patch_s_per_patch": 0.0017, "process_start_s": 6.0, "blender_start_s": 10.0}


class PipelineError(DeepCharucoError):
    """Bad pipeline input or a stage that failed: the message names the problem and the fix."""


# ---------------------------------------------------------------------------------------------- options

def parse_duration(text: str) -> float:
    """"6h", "90m", "1h30m", "45s", "2.5h" -> seconds; anything else is a `PipelineError` saying how to write it."""
    match = re.fullmatch(r"\s*(?:(\d+(?:\.\d+)?)h)?\s*(?:(\d+(?:\.\d+)?)m)?\s*(?:(\d+(?:\.\d+)?)s)?\s*", text or "")
    if not text or not match or not any(match.groups()):
        raise PipelineError(f"--budget {text!r}: give a duration such as 6h, 90m, 1h30m or 45s")
    hours, minutes, seconds = (float(g) if g else 0.0 for g in match.groups())
    total = hours * 3600 + minutes * 60 + seconds
    if total <= 0:
        raise PipelineError(f"--budget {text!r} is no time at all: give a positive duration such as 6h")
    return total


def parse_size(text: str, option: str) -> tuple[int, int]:
    """"320x240" -> (320, 240): positive multiples of 8 (ChArUcoNet's cell)."""
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.isdigit() for p in parts) or any(int(p) <= 0 or int(p) % 8 for p in parts):
        raise PipelineError(f"{option} {text!r}: give WIDTHxHEIGHT in positive multiples of 8, e.g. 320x240")
    return int(parts[0]), int(parts[1])


def human(seconds: float) -> str:
    """A duration as a person reads it: 45 s, 12 min, 3.4 h."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


class _DefaultsShown(argparse.ArgumentDefaultsHelpFormatter):
    """--help shows each default, except where there is none to show (None: the help text says what happens)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        return action.help if action.default is None else super()._get_help_string(action)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m train.pipeline", description=__doc__.splitlines()[0],
        formatter_class=_DefaultsShown,
        epilog="Sizes left out are the full plan's (family: 5000 frames, 6000 ChArUcoNet steps; board: 2000 "
               "frames, 3000 steps), reduced to fit --budget. Rerun the same command to resume after a kill.")
    target = parser.add_argument_group("what to make (exactly one)")
    target.add_argument("--family", default=None,
                        help=f"marker family for a family model: {', '.join(MARKER_FAMILIES)} (any case)")
    target.add_argument("--board", default=None, help="board file (YAML/JSON) to fine-tune a model for")
    parser.add_argument("--out", required=True, help="run folder: data, runs, detector.pt, MODEL_CARD.md")
    parser.add_argument("--budget", default=None, help="time budget for the whole pipeline, e.g. 6h, 90m, 1h30m "
                                                       "(default: no limit, the full plan)")
    parser.add_argument("--device", default="auto", help="training device: auto (CUDA, else MPS, else CPU), cpu, cuda "
                                                         "(cuda also renders on the GPU)")
    parser.add_argument("--init", default="shipped", help="weights to start from: 'shipped' (the bundle Detector() "
                                                          "loads), a bundle or checkpoint, or 'none' (from scratch)")
    parser.add_argument("--heads", choices=("all", "points"), default=None,
                        help="ChArUcoNet heads to train (default: points for --family, all for --board)")
    parser.add_argument("--width", choices=("lite", "paper"), default="lite", help="network width (both networks)")
    sizes = parser.add_argument_group("stage sizes (default: the full plan, fitted to --budget)")
    sizes.add_argument("--frames", type=int, default=None, help="training frames to render")
    sizes.add_argument("--charuconet-steps", type=int, default=None, help="ChArUcoNet optimizer steps (all stages)")
    sizes.add_argument("--refinenet-steps", type=int, default=None, help="RefineNet optimizer steps")
    sizes.add_argument("--synthetic-patches", type=int, default=None, help="synthetic X-junction patches for RefineNet")
    sizes.add_argument("--eval-sequences", type=int, default=None,
                       help="evaluation sequences per board, of the paper's 26 (a budget keeps at least "
                            f"{MIN_EVAL_SEQUENCES}; default: all 26)")
    sizes.add_argument("--eval-frames", type=int, default=40,
                       help="frames per evaluation sequence (30 well-lit, then the condition)")
    sizes.add_argument("--eval-images", type=int, default=20, help="well-lit images of the synthetic blur/darkness protocol")
    look = parser.add_argument_group("renders and training")
    look.add_argument("--image-size", default="320x240", help="rendered frame size, WxH")
    look.add_argument("--samples", type=int, default=None, help="Cycles samples per pixel (default: datagen.render's)")
    look.add_argument("--shadow-probability", type=float, default=None,
                      help="share of rendered frames (with a lamp) where an object casts its shadow on the board "
                           "(default: datagen.render's)")
    look.add_argument("--shadow-edges", type=float, default=None,
                      help="share of ChArUcoNet's training crops and of RefineNet's patches laid under a cast "
                           "shadow's edge near a corner (default: train.charuconet's and datagen.patches', 0)")
    look.add_argument("--batch-size", type=int, default=32, help="ChArUcoNet batch size")
    look.add_argument("--crop", default=None, help="ChArUcoNet training crops, WxH (default: half the frame size)")
    look.add_argument("--workers", type=int, default=2, help="DataLoader workers of the ChArUcoNet trainer")
    look.add_argument("--seed", type=int, default=0, help="render and training seed")
    look.add_argument("--nproc-per-node", type=int, default=1,
                      help="training processes (GPUs) on this machine: > 1 runs the trainers under torchrun")
    cluster = parser.add_argument_group("cluster")
    cluster.add_argument("--cluster", choices=("slurm", "k8s"), default=None,
                         help="write (not submit) a render array job and a training job for this plan, then stop")
    cluster.add_argument("--num-shards", type=int, default=16, help="--cluster: render jobs in the array")
    parser.add_argument("--plan-only", action="store_true", help="print the plan and its ETA, run nothing")
    parser.add_argument("--quiet", action="store_true", help="no progress bars from the stages")
    return parser


def stop_with_parent() -> None:
    """Run in a stage's child process before it starts (Linux): the child gets SIGTERM when the pipeline dies,
    even by SIGKILL, which no handler can pass on. A stage that outlived its pipeline kept training, and the
    rerun that resumes the run started a second trainer on the same folder."""
    import ctypes

    PR_SET_PDEATHSIG = 1
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


@dataclass
class Target:
    """What the run makes: a family model or one board's."""

    family: str | None
    board: BoardSpec | None  # the --board file's board
    heads: str

    @property
    def name(self) -> str:
        return f"family {self.family}" if self.family else f"board {self.board.squares_x}x{self.board.squares_y} {self.board.dictionary}"


def check_target(args: argparse.Namespace) -> Target:
    """--family / --board, exactly one, checked: an unknown family or an unreadable board file is refused."""
    if bool(args.family) == bool(args.board):
        raise PipelineError("give exactly one of --family FAMILY (a model for every board of a marker family) "
                            "or --board B.yaml (a model fine-tuned for one board)"
                            + (", not both" if args.family else ""))
    if args.family:
        try:  # the names `datagen.render --family` and `Detector`'s weights lookup use (DICT_4X4, APRILTAG_36H11, ...)
            families = parse_families(args.family)
        except FamilyError as exc:
            raise PipelineError(f"--family {args.family!r}: {exc}") from exc
        if len(families) != 1:
            raise PipelineError(f"--family {args.family!r}: one family per model (run the pipeline once for each)")
        return Target(families[0], None, args.heads or "points")
    return Target(None, BoardSpec.load(args.board), args.heads or "all")


def render_supports_family() -> bool:
    """Whether this checkout's ``datagen.render`` takes ``--family`` (added alongside this pipeline)."""
    result = subprocess.run([sys.executable, "-m", "datagen.render", "--help"], capture_output=True, text=True, cwd=ROOT)
    return "--family" in result.stdout


# ------------------------------------------------------------------------------------------------ rates

def load_rates(run: Path) -> dict:
    """Rates recorded by earlier stages or probes in this run folder (``rates.json``): {name: {value, source}}."""
    path = run / "rates.json"
    rates = _read_json(path)
    if rates is None and path.is_file():
        print(f"note: {path} is damaged and is ignored (the rates are measured again)", file=sys.stderr)
    return rates or {}


def record_rate(run: Path | None, name: str, value: float, source: str) -> None:
    """Remember a measured rate for later plans (a resumed run's ETA); None: a run that writes nothing (--plan-only)."""
    if run is None:
        return
    rates = load_rates(run)
    rates[name] = {"value": float(value), "source": source}
    _write_json(run / "rates.json", rates)


def probe_training_step(network: str, width: str, batch: int, size: tuple[int, int], device_name: str) -> float:
    """Seconds per optimizer step of ``network`` on random inputs (2 warm-up steps, then 3 timed): the trainer's
    cost without data loading, which runs in worker processes beside it."""
    import torch
    import torch.nn.functional as F

    from deepcharuco.cli import pick_device
    from deepcharuco.models.charuconet import ChArUcoNet, ChArUcoNetConfig
    from deepcharuco.models.refinenet import RefineNet, RefineNetConfig

    device = pick_device(device_name)
    if network == "charuconet":
        model = ChArUcoNet((ChArUcoNetConfig.lite if width == "lite" else ChArUcoNetConfig.paper)(16)).to(device)
        images = torch.rand(batch, 1, size[1], size[0], device=device)
        labels = torch.randint(0, 65, (batch, size[1] // 8, size[0] // 8), device=device)

        def loss() -> torch.Tensor:
            points, ids = model(images)
            return F.cross_entropy(points, labels) + F.cross_entropy(ids, labels % 17)
    else:
        model = RefineNet(RefineNetConfig.lite() if width == "lite" else RefineNetConfig.paper()).to(device)
        images = torch.rand(batch, 1, 24, 24, device=device)
        labels = torch.randint(0, 4096, (batch,), device=device)

        def loss() -> torch.Tensor:
            return F.cross_entropy(model(images), labels)
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-4)
    timings = []
    for step in range(5):
        started = time.perf_counter()
        optimizer.zero_grad()
        loss().backward()
        optimizer.step()
        if device.type == "cuda":
            torch.cuda.synchronize()
        if step >= 2:
            timings.append(time.perf_counter() - started)
    return float(sum(timings) / len(timings))


def probe_patches() -> float:
    """Seconds per synthetic RefineNet patch (500 made)."""
    import numpy as np

    from datagen.patches import synthetic_patches

    started = time.perf_counter()
    synthetic_patches(np.random.default_rng(0), 500)
    return (time.perf_counter() - started) / 500


def probe_render(render_args: list[str], scratch: Path) -> float:
    """Seconds per rendered frame: two frames rendered as the run will render them, one per shard; the time
    between the two shards' completion is one frame's (Blender's start-up left out)."""
    folder = scratch / "probe-render"
    command = [sys.executable, "-m", "datagen.render", *render_args, "--n", "2", "--shard-size", "1", "--out",
               str(folder), "--quiet"]
    started = time.perf_counter()
    result = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    total = time.perf_counter() - started
    if result.returncode != 0:
        raise PipelineError(f"measuring the render rate failed ({shlex.join(command)}): "
                            f"{(result.stderr.strip().splitlines() or ['no message'])[-1]}")
    shards = sorted(folder.glob("shard-*.h5"))
    between = shards[1].stat().st_mtime - shards[0].stat().st_mtime if len(shards) == 2 else 0.0
    return between if between > 0.01 else total / 2


# ------------------------------------------------------------------------------------------------- plan

@dataclass
class Sizes:
    """How much work each stage does."""

    frames: int
    charuconet_steps: int
    refinenet_steps: int
    synthetic_patches: int
    eval_sequences: int
    eval_frames: int
    eval_images: int


FULL = {"points": Sizes(5000, 6000, 2000, 20000, 26, 40, 20),
        "all": Sizes(2000, 3000, 2000, 20000, 26, 40, 20)}
FROM_SCRATCH = {"charuconet_steps": 10000, "refinenet_steps": 4000, "synthetic_patches": 100000}
SMALLEST = Sizes(frames=20, charuconet_steps=20, refinenet_steps=20, synthetic_patches=1000,
                 eval_sequences=MIN_EVAL_SEQUENCES, eval_frames=40, eval_images=4)
# How a budget is shared once the evaluation is paid for: rendering and ChArUcoNet take nearly all of it.
BUDGET_SHARE = {"frames": 0.40, "charuconet_steps": 0.50, "refinenet_steps": 0.05, "synthetic_patches": 0.05}


@dataclass
class Settings:
    """Everything that decides the result: compared when a run is resumed."""

    family: str | None
    board: dict | None
    heads: str
    init: str
    width: str
    image_size: list[int]
    samples: int | None
    shadow_probability: float | None
    shadow_edges: float | None
    batch_size: int
    crop: str
    seed: int
    sizes: dict = field(default_factory=dict)


def validation_interval(steps: int) -> int:
    """Four validations in a run, but none closer than 50 steps (a short run validates once, at its end: a
    validation costs tens of steps)."""
    return max(steps // 4, min(steps, 50))


def default_crop(image_size: tuple[int, int]) -> str:
    """Half the frame on each side (4x fewer pixels a step; the shipped recipe's 160x120 at 320x240), rounded
    down to multiples of 8; whole frames when that is under 64x48."""
    width, height = (image_size[0] // 2) // 8 * 8, (image_size[1] // 2) // 8 * 8
    return f"{width}x{height}" if width >= 64 and height >= 48 else ""


def eta_of(sizes: Sizes, rates: dict, boards: int, heads: str, from_scratch: bool) -> dict[str, float]:
    """Estimated seconds of each stage for ``sizes`` at ``rates`` (values by name)."""
    start, blender = rates["process_start_s"], rates["blender_start_s"]
    stages = 2 if from_scratch and heads == "all" else 1
    eval_frames = boards * sizes.eval_sequences * sizes.eval_frames
    # Threshold search: ~100 validation frames, 19 thresholds (markers) or one network pass (ID head).
    bundle = start + (100 * 19 * rates["detect_s_per_image"] if heads == "points" else 300 * rates["detect_s_per_image"])
    return {
        "render": blender + sizes.frames * rates["render_s_per_frame"],
        "patches": (start + (sizes.synthetic_patches + 4 * 10 * sizes.frames) * rates["patch_s_per_patch"]
                    if sizes.refinenet_steps else 0.0),
        "charuconet": stages * start + sizes.charuconet_steps * rates["charuconet_s_per_step"],
        "refinenet": start + sizes.refinenet_steps * rates["refinenet_s_per_step"] if sizes.refinenet_steps else 0.0,
        "bundle": bundle,
        "eval-data": boards * blender + eval_frames * rates["eval_render_s_per_frame"],
        "evaluate": boards * (sizes.eval_images * 22 * 2 + sizes.eval_sequences * sizes.eval_frames * 2)
                    * rates["detect_s_per_image"],
    }


def fit_to_budget(full: Sizes, fixed: dict, rates: dict, budget: float | None, boards: int, heads: str,
                  from_scratch: bool) -> tuple[Sizes, list[str]]:
    """The sizes to run: ``fixed`` (given on the command line) as given, the others the full plan's or, when
    that does not fit ``budget`` seconds, reduced (evaluation sequences first to a third of the budget, then
    frames and steps by `BUDGET_SHARE`). Returns the sizes and what was chosen, in words."""
    sizes = Sizes(**{**asdict(full), **fixed})
    if budget is None or sum(eta_of(sizes, rates, boards, heads, from_scratch).values()) <= budget:
        return sizes, []
    notes = []
    if "eval_sequences" not in fixed:
        per_sequence = sum(eta_of(Sizes(**{**asdict(sizes), "eval_sequences": 1}), rates, boards, heads,
                                  from_scratch)[k] for k in ("eval-data", "evaluate"))
        fitted = int(min(sizes.eval_sequences, max(MIN_EVAL_SEQUENCES, budget / 3 // max(per_sequence, 1e-9))))
        if fitted < sizes.eval_sequences:
            notes.append(f"evaluation: {fitted} of 26 sequences per board (full: {sizes.eval_sequences})")
            sizes.eval_sequences = fitted
    smallest = Sizes(**{**asdict(SMALLEST), **fixed, "eval_sequences": sizes.eval_sequences,
                        "eval_frames": sizes.eval_frames, "eval_images": sizes.eval_images})
    floor = eta_of(smallest, rates, boards, heads, from_scratch)
    left = budget - sum(floor.values())
    if left < 0:
        raise PipelineError(f"--budget {human(budget)} is less than the smallest plan needs (~{human(sum(floor.values()))} "
                            f"at the rates measured here): give a larger --budget, or fix smaller sizes (--frames, "
                            f"--charuconet-steps, --eval-sequences ...)")
    unit = {"frames": rates["render_s_per_frame"] + 40 * rates["patch_s_per_patch"],
            "charuconet_steps": rates["charuconet_s_per_step"], "refinenet_steps": rates["refinenet_s_per_step"],
            "synthetic_patches": rates["patch_s_per_patch"]}
    free = [k for k in BUDGET_SHARE if k not in fixed]
    share_total = sum(BUDGET_SHARE[k] for k in free) or 1.0
    for key in free:
        affordable = getattr(smallest, key) + int(left * BUDGET_SHARE[key] / share_total / unit[key])
        chosen = max(getattr(smallest, key), min(getattr(full, key), affordable))
        if chosen < getattr(full, key):
            notes.append(f"{key.replace('_', ' ')}: {chosen} (full plan: {getattr(full, key)})")
        setattr(sizes, key, chosen)
    return sizes, notes


@dataclass
class Stage:
    """One step of the plan: its name, what it does, how big it is, its ETA and how it runs."""

    name: str
    what: str
    size: str
    eta: float
    command: list[str] | None = None  # a subprocess; None: run in-process by name
    folder: Path | None = None  # a trainer's run folder (its last.pt is resumed)
    steps: int = 0
    torchrun: bool = False


class Pipeline:
    """The plan of one run folder, and running it stage by stage."""

    def __init__(self, args: argparse.Namespace, target: Target):
        self.args, self.target = args, target
        self.run = Path(args.out)
        self.image_size = parse_size(args.image_size, "--image-size")
        self.from_scratch = args.init.lower() == "none"
        self.init = "" if self.from_scratch else str(SHIPPED if args.init == "shipped" else Path(args.init))
        self.crop = default_crop(self.image_size) if args.crop is None else args.crop
        if self.crop:
            crop = parse_size(self.crop, "--crop")
            if crop[0] > self.image_size[0] or crop[1] > self.image_size[1]:
                raise PipelineError(f"--crop {self.crop} is larger than the {args.image_size} frames: choose a smaller crop")
        self.eval_boards = evaluation_boards(target)
        self.sizes: Sizes | None = None
        self.notes: list[str] = []
        self.rate_sources: dict[str, str] = {}
        # Files the plan itself needs (the board files its commands name, the render probe's scratch): in the run
        # folder, or in a temporary folder removed at exit for --plan-only, which leaves nothing behind.
        self.private = Path(tempfile.mkdtemp(prefix="deepcharuco-plan-")) if args.plan_only else self.run

    # -- settings, resumption
    def settings(self) -> Settings:
        return Settings(family=self.target.family, board=self.target.board.to_dict() if self.target.board else None,
                        heads=self.target.heads, init=str(Path(self.init).resolve()) if self.init else "none",
                        width=self.args.width, image_size=list(self.image_size), samples=self.args.samples,
                        shadow_probability=self.args.shadow_probability, shadow_edges=self.args.shadow_edges,
                        batch_size=self.args.batch_size, crop=self.crop, seed=self.args.seed)

    def fixed_sizes(self) -> dict:
        names = ("frames", "charuconet_steps", "refinenet_steps", "synthetic_patches", "eval_sequences")
        fixed = {n: getattr(self.args, n) for n in names if getattr(self.args, n) is not None}
        fixed["eval_frames"], fixed["eval_images"] = self.args.eval_frames, self.args.eval_images
        if fixed["eval_frames"] < 31:
            raise PipelineError(f"--eval-frames {fixed['eval_frames']}: give 31 or more (each evaluation sequence "
                                "starts with 30 well-lit frames, then its condition)")
        if fixed.get("refinenet_steps") == 0 and self.from_scratch:
            raise PipelineError("--refinenet-steps 0 keeps the initial weights' RefineNet, and --init none has none: "
                                "give 1 or more steps, or --init shipped (or a bundle)")
        for name, value in fixed.items():
            if name in ("refinenet_steps", "synthetic_patches") and value == 0 and not self.from_scratch:
                continue  # RefineNet kept from the initial weights: no patches, no RefineNet stage
            if value < 1 or (name == "eval_sequences" and value > 26):
                raise PipelineError(f"--{name.replace('_', '-')} {value}: give "
                                    + ("1 to 26" if name == "eval_sequences" else "a number >= 1"))
        return fixed

    def plan(self) -> None:
        """Fix the sizes: from ``plan.json`` when this folder already holds a run (which must have the same
        settings), else the full plan fitted to --budget at the rates measured now or recorded here."""
        saved_path = self.run / "plan.json"
        settings = self.settings()
        fixed = self.fixed_sizes()
        saved = _read_json(saved_path)
        if saved_path.is_file() and not (isinstance(saved, dict) and isinstance(saved.get("settings"), dict)
                                         and isinstance(saved["settings"].get("sizes"), dict)):
            if self.args.budget:  # the sizes were fitted to rates that later stages have changed: not made again
                raise PipelineError(
                    f"{saved_path} is damaged (cut off or empty) and held the sizes --budget chose: rerun with the sizes "
                    f"spelled out instead of --budget (each finished stage's command in {self.run / 'stages'} names "
                    f"them, e.g. --frames, --charuconet-steps), after moving {saved_path.name} away")
            print(f"note: {saved_path} is damaged (cut off or empty): planned again from this command (no --budget, so "
                  f"the same sizes)", file=sys.stderr)
            saved = None
        if saved is not None:
            now = asdict(settings)
            differs = [k for k in now if k != "sizes" and saved["settings"].get(k) != now[k]]
            differs += [k for k, v in fixed.items() if saved["settings"]["sizes"].get(k) != v]
            if differs:
                raise PipelineError(f"{self.run} holds a run made with other settings ({', '.join(differs)}): rerun "
                                    f"its command (in {self.run / 'plan.json'}) to resume it, or choose another --out")
            self.sizes = Sizes(**saved["settings"]["sizes"])
            self.notes = saved.get("notes", [])
            self.rates = self.measure_rates()
            return
        self.rates = self.measure_rates()
        full = FULL[self.target.heads]
        if self.from_scratch:
            full = Sizes(**{**asdict(full), **FROM_SCRATCH})
        budget = parse_duration(self.args.budget) if self.args.budget else None
        self.sizes, self.notes = fit_to_budget(full, fixed, self.rates, budget, len(self.eval_boards),
                                               self.target.heads, self.from_scratch)

    def save_plan(self) -> None:
        settings = self.settings()
        settings.sizes = asdict(self.sizes)
        _write_json(self.run / "plan.json", {"settings": asdict(settings), "notes": self.notes,
                                             "command": self.reproduce_command(), "created": _now()})

    def measure_rates(self) -> dict:
        """Each rate recorded in this folder, else measured now (training steps, patches, one render frame),
        else assumed (`ASSUMED_RATES`); where each came from is kept for the plan's printout."""
        recorded = load_rates(self.run)
        rates = {}
        for name, value in ASSUMED_RATES.items():
            rates[name] = value
            self.rate_sources[name] = "assumed"
        for name, entry in recorded.items():
            rates[name] = entry["value"]
            self.rate_sources[name] = entry["source"]
        crop = parse_size(self.crop, "--crop") if self.crop else self.image_size
        probes = {
            "charuconet_s_per_step": lambda: probe_training_step("charuconet", self.args.width, self.args.batch_size,
                                                                 crop, self.args.device),
            "refinenet_s_per_step": lambda: probe_training_step("refinenet", self.args.width, 128, (24, 24),
                                                                self.args.device),
            "patch_s_per_patch": probe_patches,
            "render_s_per_frame": lambda: probe_render(self.render_args(), self.scratch()),
        }
        for name, probe in probes.items():
            if name in recorded:
                continue
            print(f"measuring {name.replace('_', ' ')} ...", flush=True)
            rates[name] = probe()
            self.rate_sources[name] = "measured now"
            record_rate(self.record_to, name, rates[name], f"measured {_now()}")
        _remove_tree(self.scratch_root)  # the render probe's frames: timed, not kept
        if "eval_render_s_per_frame" not in recorded:
            # A sequence's frames share its renders (a static board): measured here, a frame cost about a
            # quarter of a training frame (31 frames in 17 s against 2.2 s a training frame, 160x120).
            rates["eval_render_s_per_frame"] = EVAL_RENDER_SHARE * rates["render_s_per_frame"]
            self.rate_sources["eval_render_s_per_frame"] = f"{EVAL_RENDER_SHARE} x a training render"
        return rates

    @property
    def record_to(self) -> Path | None:
        """Where measured rates are kept: the run folder, or nowhere for --plan-only (which writes nothing)."""
        return None if self.args.plan_only else self.run

    @property
    def scratch_root(self) -> Path:
        return self.private / "scratch"

    def scratch(self) -> Path:
        self.scratch_root.mkdir(parents=True, exist_ok=True)
        return Path(tempfile.mkdtemp(dir=self.scratch_root))

    # -- stage commands
    def shadow_edge_args(self) -> list[str]:
        """The shadow edges laid on training data (datagen.patches' and train.charuconet's --shadow-edges)."""
        return [] if self.args.shadow_edges is None else ["--shadow-edges", str(self.args.shadow_edges)]

    def render_args(self) -> list[str]:
        """datagen.render's arguments that decide the frames (not --n/--out)."""
        args = ["--seed", str(self.args.seed), "--width", str(self.image_size[0]), "--height", str(self.image_size[1])]
        if self.target.family:
            args += ["--family", self.target.family]
        else:
            args += ["--board", str(self.board_file())]
        if self.args.samples is not None:
            args += ["--samples", str(self.args.samples)]
        if self.args.shadow_probability is not None:
            args += ["--shadow-probability", str(self.args.shadow_probability)]
        if self.args.device.startswith("cuda"):
            args += ["--device", "gpu"]
        return args

    def board_file(self) -> Path:
        """The --board board, saved in the run folder (the run does not depend on the user's file staying put;
        --plan-only: in its temporary folder)."""
        path = self.private / "board.yaml"
        if not path.is_file():
            path.parent.mkdir(parents=True, exist_ok=True)
            self.target.board.save(path)
        return path

    def stages(self) -> list[Stage]:
        s, run, quiet = self.sizes, self.run, ["--quiet"] if self.args.quiet else []
        eta = eta_of(s, self.rates, len(self.eval_boards), self.target.heads, self.from_scratch)
        renders, patches = run / "data" / "renders", run / "data" / "patches"
        shard_size = max(1, min(100, s.frames // 10))
        stages = [
            Stage("render", f"render {s.frames} frames of " + (f"random {self.target.family} boards" if self.target.family
                                                              else "the board"),
                  f"{s.frames} frames {self.image_size[0]}x{self.image_size[1]}", eta["render"],
                  [*self.module("datagen.render"), *self.render_args(), "--n", str(s.frames), "--shard-size",
                   str(shard_size), "--out", str(renders), "--resume", *quiet]),
        ]
        if s.refinenet_steps:
            stages.append(Stage("patches", "cut corner patches and synthesise X-junctions for RefineNet",
                                f"4 per corner + {s.synthetic_patches} synthetic", eta["patches"],
                                [*self.module("datagen.patches"), "--renders", str(renders), "--out", str(patches),
                                 "--per-corner", "4", "--synthetic", str(s.synthetic_patches), "--seed",
                                 str(self.args.seed), "--overwrite", *self.shadow_edge_args()]))
        stages += self.charuconet_stages(eta["charuconet"], renders)
        last = stages[-1].folder
        # --refinenet-steps 0: the initial weights' RefineNet as it is (RefineNet is board-agnostic).
        refinenet = Path(self.init)
        if s.refinenet_steps:
            refinenet = run / "refinenet" / "best.pt"
            refine_init = [] if self.from_scratch else ["--init", self.init]
            warmup = max(1, min(100, s.refinenet_steps // 10))
            stages.append(Stage(
                "refinenet", "train RefineNet" + ("" if self.from_scratch else " from the initial weights' RefineNet"),
                f"{s.refinenet_steps} steps x 128 patches", eta["refinenet"],
                [*self.module("train.refinenet", torchrun=True), "--data", str(patches), "--out", str(run / "refinenet"),
                 "--width", self.args.width, "--steps", str(s.refinenet_steps), "--batch-size", "128",
                 "--lr", "3e-3" if self.from_scratch else "1e-3", "--warmup", str(warmup), *refine_init,
                 "--val-every", str(validation_interval(s.refinenet_steps)), "--val-batches", "40",
                 "--checkpoint-every", str(max(1, min(500, s.refinenet_steps // 4))), "--workers", "0",
                 "--seed", str(self.args.seed), "--device", self.trainer_device(), *quiet],
                folder=run / "refinenet", steps=s.refinenet_steps, torchrun=self.args.nproc_per_node > 1))
        stages.append(Stage(
            "bundle", "pack both networks; choose the score threshold on the validation shards", "1 file",
            eta["bundle"],
            [*self.module("train.bundle"), "--charuconet", str(last / "best.pt"), "--refinenet",
             str(refinenet), "--threshold", "auto", "--note", f"pipeline={self.reproduce_command()}",
             "--note", f"card={run / 'MODEL_CARD.md'}", "--out", str(run / "detector.pt")]))
        for board_name, board in self.eval_boards.items():
            folder = run / "eval" / slug(board_name)
            stages.append(Stage(
                f"eval-data {board_name}", f"render the evaluation sequences with {board_name} (never in training)",
                f"{s.eval_sequences} sequences x {s.eval_frames} frames", eta["eval-data"] / len(self.eval_boards),
                [*self.module("evaluate.paper.sequences"), "--board", str(self.eval_board_file(board_name, board)),
                 "--out", str(folder), "--frames", str(s.eval_frames), "--seed", str(1000 + self.args.seed),
                 "--width", str(self.image_size[0]), "--height", str(self.image_size[1]),
                 "--only", *SEQUENCE_PRIORITY[:s.eval_sequences], "--resume",
                 *(["--samples", str(self.args.samples)] if self.args.samples is not None else []), *quiet]))
        stages.append(Stage("evaluate", "the paper's protocols, deep vs OpenCV + cornerSubPix",
                            f"{len(self.eval_boards)} board(s), {s.eval_images} synthetic images",
                            eta["evaluate"]))
        stages.append(Stage("card", "write MODEL_CARD.md from the measured numbers", "1 file", 1.0))
        return stages

    def charuconet_stages(self, eta: float, renders: Path) -> list[Stage]:
        """One ChArUcoNet stage from the initial weights; from scratch with both heads, the shipped recipe's two:
        plain loss (30 % of the steps: the point head), then the ID term weighted 10x from its weights."""
        s, run = self.sizes, self.run
        points = self.target.heads == "points"
        common = ["--data", str(renders), "--width", self.args.width, "--batch-size", str(self.args.batch_size),
                  "--crop", self.crop, "--heads", self.target.heads, "--workers", str(self.args.workers),
                  "--seed", str(self.args.seed), "--device", self.trainer_device(), "--val-batches", "4",
                  *self.shadow_edge_args(), *(["--quiet"] if self.args.quiet else [])]
        if self.from_scratch and not points:
            plain = max(1, round(0.3 * s.charuconet_steps))
            parts = [("charuconet-a", plain, "", "1", "2e-3", "plain loss: the point head first"),
                     ("charuconet-b", s.charuconet_steps - plain, str(run / "charuconet-a" / "last.pt"), "10", "1.5e-3",
                      "ID term weighted 10x")]
            parts = [p for p in parts if p[1] > 0]
        elif points:
            parts = [("charuconet", s.charuconet_steps, self.init, "1", "2e-3" if self.from_scratch else "1e-3",
                      "point head only (ID loss off): any board of the family")]
        else:
            parts = [("charuconet", s.charuconet_steps, self.init, "10", "1.5e-3",
                      "point and ID heads on this board, from the initial weights")]
        stages = []
        for name, steps, init, id_weight, lr, why in parts:
            folder = run / name
            stages.append(Stage(
                name, f"train ChArUcoNet: {why}", f"{steps} steps x {self.args.batch_size} crops {self.crop or 'whole'}",
                eta * steps / s.charuconet_steps,
                [*self.module("train.charuconet", torchrun=True), *common, "--out", str(folder), "--steps", str(steps),
                 "--lr", lr, "--warmup", str(max(1, min(300, steps // 10))),
                 *(["--id-positive-weight", id_weight] if not points else []), *(["--init", init] if init else []),
                 "--val-every", str(validation_interval(steps)), "--checkpoint-every", str(max(1, min(500, steps // 10)))],
                folder=folder, steps=steps, torchrun=self.args.nproc_per_node > 1))
        return stages

    def trainer_device(self) -> str:
        # Under torchrun each rank must take its own GPU: "auto" picks cuda:LOCAL_RANK, a bare "cuda" would
        # put every rank on the first GPU.
        return "auto" if self.args.nproc_per_node > 1 and self.args.device == "cuda" else self.args.device

    def module(self, name: str, torchrun: bool = False) -> list[str]:
        if torchrun and self.args.nproc_per_node > 1:
            return ["torchrun", "--standalone", "--nproc-per-node", str(self.args.nproc_per_node), "-m", name]
        return [sys.executable, "-m", name]

    def eval_board_file(self, name: str, board: BoardSpec) -> Path:
        path = self.private / "eval" / f"{slug(name)}.yaml"
        if not path.is_file():
            path.parent.mkdir(parents=True, exist_ok=True)
            board.save(path)
        return path

    def reproduce_command(self) -> str:
        """The command that makes the same weights: every size spelled out (a --budget depends on the rates
        measured, so it is replaced by the sizes it chose)."""
        a, s = self.args, self.sizes
        parts = ["python", "-m", "train.pipeline"]
        parts += ["--family", a.family] if a.family else ["--board", str(Path(a.board))]
        parts += ["--out", str(self.run), "--init", a.init,
                  "--heads", self.target.heads, "--width", a.width, "--image-size", a.image_size,
                  "--batch-size", str(a.batch_size), "--crop", self.crop, "--seed", str(a.seed)]
        if a.samples is not None:
            parts += ["--samples", str(a.samples)]
        if a.shadow_probability is not None:
            parts += ["--shadow-probability", str(a.shadow_probability)]
        parts += self.shadow_edge_args()
        if s is not None:
            parts += ["--frames", str(s.frames), "--charuconet-steps", str(s.charuconet_steps),
                      "--refinenet-steps", str(s.refinenet_steps), "--synthetic-patches", str(s.synthetic_patches),
                      "--eval-sequences", str(s.eval_sequences), "--eval-frames", str(s.eval_frames),
                      "--eval-images", str(s.eval_images)]
        return shlex.join(parts)

    # -- running
    def print_plan(self, stages: list[Stage]) -> None:
        done = [self.is_done(stage) for stage in stages]
        print(f"plan for {self.target.name} in {self.run} ({self.target.heads} heads, {self.args.width} width, "
              f"init: {self.init or 'none (from scratch)'})")
        name_width = max(len(stage.name) for stage in stages)
        for number, (stage, finished) in enumerate(zip(stages, done), 1):
            state = "done" if finished else f"~{human(stage.eta)}"
            print(f"  {number}. {stage.name:<{name_width}}  {stage.size:<40} {state}")
        left = sum(stage.eta for stage, finished in zip(stages, done) if not finished)
        finish = dt.datetime.now() + dt.timedelta(seconds=left)
        print(f"  ETA: {human(left)} left (about {finish:%Y-%m-%d %H:%M})"
              + (f", budget {human(parse_duration(self.args.budget))}" if self.args.budget else ""))
        used = {k: v for k, v in self.rates.items() if not k.endswith("start_s")}
        print("  rates: " + "; ".join(f"{k} {v:.4g} ({self.rate_sources.get(k, '?')})" for k, v in used.items()))
        for note in self.notes:
            print(f"  fitted to the budget: {note}")
        print(f"  reproduce: {self.reproduce_command()}", flush=True)

    def marker(self, stage: Stage) -> Path:
        return self.run / "stages" / f"{slug(stage.name)}.json"

    def finished(self, stage: Stage) -> bool:
        """The stage recorded that it finished (a readable marker), or, for a trainer, its last.pt reached its
        steps (trained elsewhere, e.g. by the cluster job)."""
        if _read_json(self.marker(stage)) is not None:
            return True
        return bool(stage.folder and stage.steps and _checkpoint_step(stage.folder / "last.pt") >= stage.steps)

    def is_done(self, stage: Stage) -> bool:
        """A stage is done when it finished and its outputs read back complete: a marker alone is not enough (a
        deleted shard, a cut-off checkpoint)."""
        return self.finished(stage) and not self.damaged_files(stage) and self.missing_output(stage) is None

    # -- what the stages left, checked
    def outputs(self, stage: Stage) -> tuple[str, Path]:
        """(kind, path) of what ``stage`` makes: "frames" / "patches" (a folder of shards), "checkpoints" (a
        trainer's folder), "checkpoint", "json" or "text" (one file)."""
        name = stage.name
        if name == "render":
            return "frames", self.run / "data" / "renders"
        if name == "patches":
            return "patches", self.run / "data" / "patches"
        if stage.folder is not None:
            return "checkpoints", stage.folder
        if name == "bundle":
            return "checkpoint", self.run / "detector.pt"
        if name.startswith("eval-data "):
            return "frames", self.run / "eval" / slug(name[len("eval-data "):])
        if name == "evaluate":
            return "json", self.run / "eval" / "results.json"
        return "text", self.run / "MODEL_CARD.md"

    def damaged_files(self, stage: Stage) -> list[tuple[Path, str]]:
        """(file, why) for each file of ``stage``'s outputs that exists but does not read back."""
        kind, path = self.outputs(stage)
        if kind in ("frames", "patches"):
            if not path.is_dir():
                return []
            read = ShardReader if kind == "frames" else read_patch_shard
            return [(shard, why) for shard in list_shards(path) if (why := _unreadable(read, shard))]
        if kind == "checkpoints":
            return [(p, why) for p in (path / "last.pt", path / "best.pt") if p.is_file()
                    and (why := _unreadable(_load_checkpoint, p))]
        if not path.is_file():
            return []
        why = _unreadable(_load_checkpoint, path) if kind == "checkpoint" else (
            None if kind == "text" or _read_json(path) is not None else "not valid JSON (cut off?)")
        return [(path, why)] if why else []

    def missing_output(self, stage: Stage) -> str | None:
        """What a finished ``stage`` should have made and has not (a deleted shard, a missing file), or None."""
        kind, path = self.outputs(stage)
        if kind == "frames":
            if not path.is_dir() or not list_shards(path):
                return f"{path} holds no shards"
            if stage.name == "render":
                frames = sum(_frames_in(p) for p in list_shards(path))
                if frames < self.sizes.frames:
                    return f"{path} holds {frames} of the plan's {self.sizes.frames} frames"
            return None
        if kind == "patches":
            return None if path.is_dir() and list_shards(path) else f"{path} holds no patch shards"
        if kind == "checkpoints":
            missing = [p.name for p in (path / "last.pt", path / "best.pt") if not p.is_file()]
            if missing:
                return f"{path} has no {' or '.join(missing)}"
            step = _checkpoint_step(path / "last.pt")
            return None if step >= stage.steps else f"{path / 'last.pt'} is at step {step} of {stage.steps}"
        if not path.is_file() or path.stat().st_size == 0:
            return f"{path} is missing or empty"
        return None

    def repair(self, stages: list[Stage]) -> None:
        """Before running: move each damaged output aside (``NAME.damaged``, kept for a look), and mark a stage
        whose outputs do not verify as not done, saying what is redone. A trainer whose last.pt is damaged
        resumes from its best.pt (a full checkpoint of an earlier step) where that reads, else starts again."""
        for stage in stages:
            damaged = self.damaged_files(stage)
            for path, why in damaged:
                aside = path.with_name(path.name + ".damaged")
                os.replace(path, aside)
                print(f"note: {path} is damaged ({why}): moved to {aside.name}; stage {stage.name} makes it again",
                      file=sys.stderr)
            if stage.folder is not None and any(p.name == "last.pt" for p, _ in damaged):
                best = stage.folder / "best.pt"
                if best.is_file():
                    shutil.copyfile(best, stage.folder / "last.pt")
                    print(f"note: stage {stage.name} resumes from {best} (step {_checkpoint_step(best)}), its last "
                          f"good checkpoint", file=sys.stderr)
                else:
                    print(f"note: stage {stage.name} has no good checkpoint left: it starts again", file=sys.stderr)
            marker = self.marker(stage)
            if marker.exists() and (_read_json(marker) is None or damaged or self.missing_output(stage)):
                why = self.missing_output(stage) or ("its record is damaged" if not damaged else "damaged outputs")
                marker.unlink()
                print(f"note: stage {stage.name} is not done ({why}): it runs again", file=sys.stderr)

    def execute(self, stages: list[Stage]) -> int:
        """Run the stages not done yet, in order; 0 when all are done, the stopping signal's 128 + n after a
        Ctrl-C / SIGTERM (the stage in progress saved what it had: rerun to continue)."""
        for number, stage in enumerate(stages, 1):
            if self.is_done(stage):
                continue
            print(f"\n== stage {number}/{len(stages)}: {stage.name}: {stage.what} ({stage.size}, ~{human(stage.eta)})",
                  flush=True)
            started = time.perf_counter()
            if stage.command is None:
                result = self.run_in_process(stage)
            else:
                code, result = self.run_subprocess(stage)
                if code in (130, 143, -signal.SIGINT, -signal.SIGTERM):
                    print(f"stopped during stage {stage.name}: rerun the same command to continue", file=sys.stderr)
                    return 130 if code in (130, -signal.SIGINT) else 143
                if code != 0:
                    raise PipelineError(f"stage {stage.name} failed (exit code {code}; its message is above): fix what "
                                        f"it says and rerun the same command, finished stages are kept. The command "
                                        f"was: {shlex.join(stage.command)}")
            seconds = time.perf_counter() - started
            self.record(stage, seconds, result)
            _write_json(self.marker(stage), {"stage": stage.name, "command": shlex.join(stage.command) if stage.command
                                             else None, "seconds": round(seconds, 1), "finished": _now(),
                                             "result": result})
        print(f"\ndone: {self.run / 'detector.pt'} (Detector(weights=...), detect --weights); card "
              f"{self.run / 'MODEL_CARD.md'}")
        return 0

    def run_subprocess(self, stage: Stage) -> tuple[int, dict]:
        """Run a stage's command (trainers resumed from their last.pt); SIGINT/SIGTERM sent to this process are
        passed on to it, so it stops as it would on its own (a trainer saves last.pt)."""
        command = list(stage.command)
        if stage.folder is not None:
            if (stage.folder / "last.pt").is_file():
                command.append("--resume")
            else:  # a kill before the first checkpoint: what it logged belongs to no checkpoint
                for leftover in ("log.csv", "best.pt"):
                    (stage.folder / leftover).unlink(missing_ok=True)
        for leftover in (self.run / "data").glob(".patches.tmp-*") if stage.name == "patches" else ():
            _remove_tree(leftover)  # a patches stage killed before it could clean up (SIGKILL)
        before = self.progress(stage)
        print("$ " + shlex.join(command), flush=True)
        process = subprocess.Popen(command, cwd=ROOT, preexec_fn=stop_with_parent if sys.platform == "linux" else None)
        forwarded = []

        def forward(signum, frame):
            forwarded.append(signum)
            process.send_signal(signum)

        previous = {sig: signal.signal(sig, forward) for sig in (signal.SIGINT, signal.SIGTERM)}
        try:
            code = process.wait()
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        if forwarded and code == 0:
            code = 128 + forwarded[0]
        if stage.name == "bundle" and code == 0:
            return code, bundle_summary(self.run / "detector.pt")
        return code, {"progress_before": before, "progress_after": self.progress(stage)}

    def progress(self, stage: Stage) -> int:
        """How far a resumable stage got: frames rendered, or a trainer's step."""
        if stage.name == "render":
            index = self.run / "data" / "renders" / "index.json"
            return int(json.loads(index.read_text()).get("frames", 0)) if index.is_file() else 0
        if stage.folder is not None:
            return _checkpoint_step(stage.folder / "last.pt")
        return 0

    def record(self, stage: Stage, seconds: float, result: dict) -> None:
        """Rates measured by a finished stage, for the ETA of later plans."""
        work = result.get("progress_after", 0) - result.get("progress_before", 0)
        if stage.name == "render" and work > 0:
            record_rate(self.run, "render_s_per_frame", max(0.0, seconds - self.rates["blender_start_s"]) / work,
                        f"render stage {_now()}")
        elif stage.name.startswith("charuconet") and work > 0:
            record_rate(self.run, "charuconet_s_per_step", seconds / work, f"{stage.name} stage {_now()}")
        elif stage.name == "refinenet" and work > 0:
            record_rate(self.run, "refinenet_s_per_step", seconds / work, f"refinenet stage {_now()}")
        elif stage.name.startswith("eval-data"):
            frames = self.sizes.eval_sequences * self.sizes.eval_frames
            record_rate(self.run, "eval_render_s_per_frame", max(0.0, seconds - self.rates["blender_start_s"]) / frames,
                        f"{stage.name} stage {_now()}")

    def run_in_process(self, stage: Stage) -> dict:
        if stage.name == "evaluate":
            results = evaluate_model(self.run / "detector.pt", self.eval_boards, self.run / "eval", self.sizes,
                                     self.args.quiet)
            _write_json(self.run / "eval" / "results.json", results)
            return {"results": str(self.run / "eval" / "results.json")}
        if stage.name == "card":
            write_card(self)
            return {"card": str(self.run / "MODEL_CARD.md")}
        raise AssertionError(stage.name)


# ------------------------------------------------------------------------------------------- evaluation

def slug(name: str) -> str:
    return re.sub(r"[^a-z0-9_.-]+", "-", name.lower()).strip("-")


def evaluation_boards(target: Target) -> dict[str, BoardSpec]:
    """Boards to evaluate on: for a family, the family's boards of `evaluate.paper.unseen_boards` (or a 6x5 board of
    the family's dictionary) and, for DICT_5X5, the paper's board; for --board, that board."""
    if target.board is not None:
        return {f"{target.board.squares_x}x{target.board.squares_y} {target.board.dictionary}": target.board}
    from evaluate.paper.unseen_boards import UNSEEN_BOARDS

    dictionary = MARKER_FAMILIES[target.family][-1]  # the largest: the _50/_100/_250 ones are its prefixes
    boards = {name: board for name, board in UNSEEN_BOARDS.items() if marker_family(board.dictionary) == target.family}
    if not boards:
        boards = {f"6x5 {dictionary}": BoardSpec(squares_x=6, squares_y=5, square_length=0.04, marker_length=0.03,
                                                 dictionary=dictionary)}
    if target.family == "DICT_5X5":
        boards["5x5 DICT_5X5_50 (the paper's)"] = BoardSpec()
    return boards


def evaluate_model(weights: Path, boards: dict[str, BoardSpec], root: Path, sizes: Sizes, quiet: bool) -> dict:
    """Per board: the synthetic blur/darkness protocol and the sequences' pose accuracy, the bundle (as
    `Detector(board=...)` uses it) next to OpenCV + cornerSubPix on the same frames; and the bundle's speed."""
    from deepcharuco.deep_detector import Detector
    from deepcharuco.opencv_detector import OpenCVDetector
    from evaluate.paper import experiments
    from evaluate.paper.data import load_frames, select_well_lit
    from evaluate.paper.protocols import LEVELS
    from evaluate.paper.unseen_boards import board_summary

    results = {}
    for name, board in boards.items():
        frames = load_frames(root / slug(name), board)
        detectors = {"deep": Detector(board=board, weights=weights), "opencv": OpenCVDetector(board, refine="subpix")}
        well_lit = select_well_lit(frames, min(sizes.eval_images, len({f.meta.get("sequence") for f in frames})))
        synthetic = experiments.synthetic_experiment(detectors, well_lit, LEVELS, quiet)
        sequences = experiments.sequence_experiment(detectors, frames, f"sequences {name}", quiet)
        summary = board_summary(list(detectors), synthetic, sequences)
        results[name] = {"board": board.to_dict(), "geometry": detectors["deep"].geometry, "frames": len(frames),
                         "synthetic_images": len(well_lit), "summary": summary,
                         "sequences": [{"sequence": row.get("sequence"), "lux": row.get("lux"),
                                        **{d: {"pose_accuracy": row[d].get("pose_accuracy")} for d in detectors}}
                                       for row in sequences["table"]]}
        results[name]["fps_320x240"] = measure_fps(detectors["deep"], frames[:10])
    return {"boards": results, "weights": str(weights), "created": _now()}


def measure_fps(detector, frames: list, seconds: float = 2.0) -> float:
    """Frames per second of detect + pose at 320x240 (frames resized to it), over ``seconds``."""
    import cv2

    images = [cv2.resize(f.image, (320, 240), interpolation=cv2.INTER_AREA) for f in frames]
    camera = frames[0].K * [[320 / frames[0].image.shape[1]], [240 / frames[0].image.shape[0]], [1]]
    done, started = 0, time.perf_counter()
    while time.perf_counter() - started < seconds or done < len(images):
        detector.estimate_pose(detector.detect(images[done % len(images)]), camera, None)
        done += 1
    return done / (time.perf_counter() - started)


def bundle_summary(path: Path) -> dict:
    """What the card needs from the bundle: the threshold, each network's steps and validation metrics."""
    from deepcharuco.models.checkpoint import id_head_trained, read_checkpoint

    charuconet, refinenet = read_checkpoint(path, "charuconet"), read_checkpoint(path, "refinenet")
    return {"threshold": charuconet.get("threshold"), "id_head_trained": id_head_trained(charuconet),
            "charuconet": {"step": charuconet["training"].get("step"), "metrics": charuconet["training"].get("metrics")},
            "refinenet": {"step": refinenet["training"].get("step"), "metrics": refinenet["training"].get("metrics")},
            "size_mb": round(path.stat().st_size / 1e6, 2)}


# ------------------------------------------------------------------------------------------------- card

def write_card(pipeline: Pipeline) -> Path:
    """MODEL_CARD.md: what the weights are, the command that makes them again, the stages as run (commands and
    times), the numbers measured by the evaluation stage and what was chosen on which data."""
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
        lines.append(f"| {stage.name} | {stage.size} | {human(record['seconds']) if record else 'this stage'} | "
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


# ---------------------------------------------------------------------------------------------- cluster

def write_cluster_scripts(pipeline: Pipeline, kind: str, num_shards: int) -> list[Path]:
    """A render array job over ``--shard-index/--num-shards`` and a training job that runs this pipeline (its
    trainers under torchrun when --nproc-per-node > 1); written to ``OUT/cluster``, not submitted."""
    if num_shards < 1:
        raise PipelineError(f"--num-shards {num_shards}: give 1 or more render jobs")
    stages = pipeline.stages()
    render = next(s for s in stages if s.name == "render")
    render_command = [a for a in render.command if a not in ("--resume", "--quiet")]
    render_command[0] = "python"
    per_job = pipeline.rates["render_s_per_frame"] * pipeline.sizes.frames / num_shards
    hours = max(1, math.ceil(2 * (per_job + 600) / 3600))  # twice the estimate, at least an hour
    folder = pipeline.run / "cluster"
    folder.mkdir(parents=True, exist_ok=True)
    pipeline_command = pipeline.reproduce_command()
    gpus = max(1, pipeline.args.nproc_per_node)
    ddp_note = ("# Training: train/loop.py supports torchrun (DDP): each rank takes every world-size-th sample of a\n"
                "# batch, rank 0 writes checkpoints and logs; one node, one process per GPU (--device auto gives rank r\n"
                "# the GPU LOCAL_RANK). Run with 2 CPU processes (gloo) only, never on several GPUs yet. Stop the job as\n"
                "# a whole (a rank stopped alone leaves the others waiting), then resume it.\n"
                f"# Paths are those of the checkout that wrote this ({ROOT}): edit them for the cluster's mounts.\n")
    if kind == "slurm":
        render_path, train_path = folder / "render.slurm", folder / "train.slurm"
        write_atomic(render_path,
            "#!/bin/bash\n"
            f"# Render stage of {pipeline.run} as a SLURM array: job i renders the shards i, i+{num_shards}, ...\n"
            f"# Submit: sbatch {render_path}; then: sbatch --dependency=afterok:JOBID {train_path}\n"
            f"#SBATCH --job-name=deepcharuco-render\n#SBATCH --array=0-{num_shards - 1}\n#SBATCH --cpus-per-task=8\n"
            f"#SBATCH --time={hours}:00:00\n#SBATCH --output={folder}/render-%A_%a.log\n"
            "set -euo pipefail\n"
            f"cd {shlex.quote(str(ROOT))}\nsource .venv/bin/activate\n"
            f"{shlex.join(render_command)} --shard-index \"$SLURM_ARRAY_TASK_ID\" --num-shards {num_shards} "
            "--threads \"$SLURM_CPUS_PER_TASK\" --resume --quiet\n")
        write_atomic(train_path,
            "#!/bin/bash\n" + ddp_note +
            f"# The rest of the pipeline (patches, training, bundle, evaluation, card) on one node with {gpus} GPU(s).\n"
            f"#SBATCH --job-name=deepcharuco-train\n#SBATCH --nodes=1\n#SBATCH --gpus-per-node={gpus}\n"
            f"#SBATCH --cpus-per-task=16\n#SBATCH --time=24:00:00\n#SBATCH --output={folder}/train-%j.log\n"
            "set -euo pipefail\n"
            f"cd {shlex.quote(str(ROOT))}\nsource .venv/bin/activate\n"
            f"{pipeline_command} --device cuda --nproc-per-node {gpus} --quiet\n")
        return [render_path, train_path]
    render_path, train_path = folder / "render-job.yaml", folder / "train-job.yaml"
    image = "deepcharuco:latest  # an image with this repository at /work and its .venv"
    write_atomic(render_path,
        f"# Render stage of {pipeline.run} as a Kubernetes Indexed Job: pod i renders the shards i, i+{num_shards}, ...\n"
        f"# The run folder must be on a volume every pod mounts (here the PVC deepcharuco-runs at /work/{pipeline.run}).\n"
        f"# Apply: kubectl apply -f {render_path}; when it completes: kubectl apply -f {train_path}\n"
        "apiVersion: batch/v1\nkind: Job\nmetadata:\n  name: deepcharuco-render\nspec:\n"
        f"  completions: {num_shards}\n  parallelism: {num_shards}\n  completionMode: Indexed\n  backoffLimitPerIndex: 3\n"
        "  template:\n    spec:\n      restartPolicy: Never\n      containers:\n      - name: render\n"
        f"        image: {image}\n        workingDir: /work\n"
        "        command: [\"/bin/bash\", \"-c\"]\n"
        f"        args: [{json.dumps(shlex.join(render_command) + ' --shard-index $JOB_COMPLETION_INDEX --num-shards ' + str(num_shards) + ' --resume --quiet')}]\n"
        "        resources: {requests: {cpu: \"8\", memory: 8Gi}}\n"
        f"        volumeMounts: [{{name: runs, mountPath: /work/{pipeline.run}}}]\n"
        "      volumes: [{name: runs, persistentVolumeClaim: {claimName: deepcharuco-runs}}]\n")
    write_atomic(train_path,
        ddp_note +
        "apiVersion: batch/v1\nkind: Job\nmetadata:\n  name: deepcharuco-train\nspec:\n  backoffLimit: 3\n"
        "  template:\n    spec:\n      restartPolicy: OnFailure  # a rerun resumes where the pod stopped\n"
        "      containers:\n      - name: train\n"
        f"        image: {image}\n        workingDir: /work\n        command: [\"/bin/bash\", \"-c\"]\n"
        f"        args: [{json.dumps(pipeline_command + f' --device cuda --nproc-per-node {gpus} --quiet')}]\n"
        f"        resources: {{limits: {{nvidia.com/gpu: {gpus}}}, requests: {{cpu: \"16\", memory: 32Gi}}}}\n"
        f"        volumeMounts: [{{name: runs, mountPath: /work/{pipeline.run}}}]\n"
        "      volumes: [{name: runs, persistentVolumeClaim: {claimName: deepcharuco-runs}}]\n")
    return [render_path, train_path]


# ------------------------------------------------------------------------------------------------ utils

def _now() -> str:
    return dt.datetime.now(dt.timezone.utc).replace(microsecond=0).isoformat()


def _write_json(path: Path, data) -> None:
    """Write atomically: a kill leaves the previous file or the new one, never half of one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, json.dumps(data, indent=1, default=str) + "\n")


def _checkpoint_step(path: Path) -> int:
    """The step a trainer's checkpoint reached; 0 without one or with one that does not read (`repair` says so)."""
    if not path.is_file():
        return 0
    try:
        return int(_load_checkpoint(path)["training"]["step"])
    except Exception:  # noqa: BLE001 - any unreadable checkpoint: torch raises RuntimeError, EOFError, pickle errors
        return 0


def _load_checkpoint(path: Path) -> dict:
    import torch

    state = torch.load(path, map_location="cpu", weights_only=False)
    if not isinstance(state, dict):
        raise ValueError("not a checkpoint of this project")
    return state


def _unreadable(read, path: Path) -> str | None:
    """None when ``read(path)`` succeeds, else why it failed (one line)."""
    try:
        result = read(path)
        if hasattr(result, "close"):
            result.close()
    except Exception as error:  # noqa: BLE001 - a damaged file can fail any way its reader does
        first = (str(error).splitlines() or [type(error).__name__])[0]
        return first.split(". ")[0][:160]  # its first sentence: torch's go on with advice for another situation
    return None


def _frames_in(shard: Path) -> int:
    """The frames a frame shard holds; 0 when it does not read (opened once)."""
    try:
        return len(ShardReader(shard))
    except Exception:  # noqa: BLE001 - a damaged shard fails as its reader does: `damaged_files` says how
        return 0


def _read_json(path: Path):
    """The JSON in ``path``; None when it is missing, empty, cut off or not JSON."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)

    def body() -> int:
        target = check_target(args)
        if args.budget is not None:
            parse_duration(args.budget)
        if args.nproc_per_node < 1 or args.batch_size < 1 or args.workers < 0:
            raise PipelineError("--nproc-per-node and --batch-size must be >= 1, --workers >= 0")
        if args.shadow_probability is not None and not 0.0 <= args.shadow_probability <= 1.0:
            raise PipelineError(f"--shadow-probability {args.shadow_probability}: give a probability in [0, 1]")
        if args.shadow_edges is not None and not 0.0 <= args.shadow_edges <= 1.0:
            raise PipelineError(f"--shadow-edges {args.shadow_edges}: give a share of the crops and patches in [0, 1]")
        if args.init.lower() not in ("none", "shipped") and not Path(args.init).is_file():
            raise PipelineError(f"--init {args.init} does not exist: give a bundle or checkpoint, or 'none' to "
                                "train from scratch")
        pipeline = Pipeline(args, target)
        try:
            return plan_and_run(args, target, pipeline)
        finally:
            if args.plan_only:
                _remove_tree(pipeline.private)

    return run_command(body)


def plan_and_run(args: argparse.Namespace, target: Target, pipeline: Pipeline) -> int:
    """Plan the run in ``args.out``, then print it (--plan-only), write the cluster scripts (--cluster) or run it."""
    pipeline.fixed_sizes()
    if args.plan_only:
        check_output_folder(args.out)
    else:
        output_folder(args.out)
    if target.family and not render_supports_family():
        raise PipelineError("this checkout's datagen.render has no --family option yet (python -m datagen.render "
                            "--help): render one board with --board B.yaml, or update the checkout")
    pipeline.plan()
    stages = pipeline.stages()
    if not args.plan_only and not args.cluster:
        pipeline.repair(stages)
    pipeline.print_plan(stages)
    if args.cluster:
        for path in write_cluster_scripts(pipeline, args.cluster, args.num_shards):
            print(f"wrote {path}")
        return 0
    if args.plan_only:
        return 0
    pipeline.save_plan()
    # Outside a stage's subprocess (which gets the signal passed on), a SIGTERM ends the run as Ctrl-C does:
    # nothing half-made is recorded as done, and the exit code says which signal stopped it.
    signal.signal(signal.SIGTERM, _stop_by_sigterm)
    try:
        return pipeline.execute(stages)
    except KeyboardInterrupt as stop:
        print(f"stopped: rerun the same command to continue ({pipeline.run} keeps every finished stage)",
              file=sys.stderr)
        return 143 if stop.args == ("SIGTERM",) else 130


def _stop_by_sigterm(signum, frame) -> None:
    raise KeyboardInterrupt("SIGTERM")


def _remove_tree(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
