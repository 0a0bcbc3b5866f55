"""The plan of a run: what it makes (a family's model or one board's), how big each stage is, and those sizes
fitted to a time budget at the rates measured (`train.pipeline.rates`). No file is read or written here."""

from __future__ import annotations

import argparse
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path

from datagen.family import FamilyError, parse_families
from deepcharuco.boards.board import BoardSpec
from deepcharuco.core.errors import DeepCharucoError

ROOT = Path(__file__).resolve().parents[2]  # the repository's root (this file: train/pipeline/plan.py)
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
