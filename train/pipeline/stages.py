"""The stages of a run and their commands: `Pipeline` fixes the plan of one run folder (kept in ``plan.json``,
compared when the run is resumed) and lists its `Stage`s, each a subprocess (``python -m datagen.render``,
``train.charuconet`` ...) or an in-process step; `train.pipeline.run` runs them."""

from __future__ import annotations

import argparse
import datetime as dt
import shlex
import sys
import tempfile
from dataclasses import asdict
from pathlib import Path

from deepcharuco.boards.board import BoardSpec
from train.pipeline.checks import is_done
from train.pipeline.evaluation import evaluation_boards
from train.pipeline.plan import (
    ASSUMED_RATES, EVAL_RENDER_SHARE, FROM_SCRATCH, FULL, SEQUENCE_PRIORITY, SHIPPED, PipelineError, Settings,
    Sizes, Stage, Target, default_crop, eta_of, fit_to_budget, human, parse_duration, parse_size,
    validation_interval,
)
from train.pipeline.rates import load_rates, probe_patches, probe_render, probe_training_step, record_rate
from train.pipeline.records import now, read_json, remove_tree, slug, write_json


class Pipeline:
    """The plan of one run folder (its sizes, fixed at the first run) and the commands of its stages; checked by
    `train.pipeline.checks`, run by `train.pipeline.run`."""

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
        saved = read_json(saved_path)
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
        write_json(self.run / "plan.json", {"settings": asdict(settings), "notes": self.notes,
                                             "command": self.reproduce_command(), "created": now()})

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
            record_rate(self.record_to, name, rates[name], f"measured {now()}")
        remove_tree(self.scratch_root)  # the render probe's frames: timed, not kept
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
        shard_size = self.render_shard_size
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

    @property
    def render_shard_size(self) -> int:
        """Frames per render shard: a tenth of the frames, 1 to 100 (a shard is the unit a resumed or split
        render redoes)."""
        return max(1, min(100, self.sizes.frames // 10))

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

    # -- the plan, printed
    def print_plan(self, stages: list[Stage]) -> None:
        done = [is_done(self.run, stage, self.sizes.frames) for stage in stages]
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
