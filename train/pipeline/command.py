"""One command makes a model: ``python -m train.pipeline --family DICT_4X4 --out runs/4x4 [--budget 6h]``.

The command line: its options, their checks, and the order of work (plan, repair, print, then the cluster
scripts or the run). ``train.pipeline``'s docstring lists the stages.
"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
from pathlib import Path

from deepcharuco.boards.dictionaries import MARKER_FAMILIES
from deepcharuco.cli.common import check_output_folder, output_folder, run_command
from train.pipeline.checks import repair
from train.cluster import slurm
from train.pipeline.cluster import DEFAULT_CPUS, on_slurm
from train.pipeline.kubernetes import write_manifests
from train.pipeline.plan import MIN_EVAL_SEQUENCES, ROOT, PipelineError, Target, check_target, parse_duration
from train.pipeline.records import remove_tree
from train.pipeline.run import execute, run_stage
from train.pipeline.stages import Pipeline


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
    cluster = parser.add_argument_group("cluster (docs/training.md, On a cluster)")
    cluster.add_argument("--cluster", choices=("slurm", "k8s"), default=None,
                         help="slurm: write a job script per stage (the render an array job) to OUT/cluster, and with "
                              "--submit submit, follow and recover them; k8s: write Kubernetes Job manifests")
    cluster.add_argument("--submit", action="store_true",
                         help="--cluster slurm: submit the stages not done yet, chained with --dependency=afterok, and "
                              "follow them until the run is done (resubmitting failed array tasks)")
    cluster.add_argument("--no-wait", action="store_true", help="--submit: exit after submitting, printing the job IDs")
    cluster.add_argument("--status", action="store_true", help="--cluster slurm: say where each stage of the run stands")
    cluster.add_argument("--num-shards", type=int, default=16, help="render tasks in the array (at most one per shard)")
    cluster.add_argument("--partition", default=None, help="SLURM partition (default: the cluster's default)")
    cluster.add_argument("--cpus-per-task", type=int, default=None,
                         help=f"CPUs per job and per render task (default: {DEFAULT_CPUS}, or the nodes' CPUs if fewer)")
    cluster.add_argument("--mem", default=None, help="memory per job, e.g. 16G (default: 4G render, 16G trainers, "
                                                     "8G the rest, or the nodes' memory if less)")
    cluster.add_argument("--gpus", type=int, default=None,
                         help="GPUs per trainer job (--gres=gpu:N; N > 1 runs the trainer under torchrun with N "
                              "processes; default: --nproc-per-node with --device cuda, else none)")
    cluster.add_argument("--time", default=None, help="time limit per job, e.g. 4:00:00 (default: twice the stage's "
                                                      "ETA plus 10 minutes, at least 15 minutes)")
    cluster.add_argument("--max-retries", type=int, default=2,
                         help="--submit: times a failed job or array task is resubmitted before the run stops")
    cluster.add_argument("--poll", type=float, default=10.0, help="--submit: seconds between looks at the queue")
    cluster.add_argument("--stage", default=None, help="run this one stage (what each cluster job runs); its earlier "
                                                       "stages must be done")
    cluster.add_argument("--shard-index", type=int, default=None,
                         help="--stage render: render only this array task's shards (index of --num-shards)")
    parser.add_argument("--plan-only", action="store_true", help="print the plan and its ETA, run nothing")
    parser.add_argument("--quiet", action="store_true", help="no progress bars from the stages")
    return parser


def check_cluster_options(args: argparse.Namespace) -> None:
    """The cluster options agree with each other, and ``--submit``/``--status`` find SLURM's commands."""
    if (args.submit or args.status or args.no_wait) and args.cluster != "slurm":
        raise PipelineError("--submit, --no-wait and --status go with --cluster slurm")
    if args.no_wait and not args.submit:
        raise PipelineError("--no-wait goes with --submit (submit, print the job IDs and exit)")
    if args.num_shards < 1:
        raise PipelineError(f"--num-shards {args.num_shards}: give 1 or more render tasks")
    if args.stage and (args.cluster or args.plan_only):
        raise PipelineError("--stage runs one stage here (as a cluster job does): leave out --cluster and --plan-only")
    if args.shard_index is not None and not (args.stage == "render" and 0 <= args.shard_index < args.num_shards):
        if args.stage != "render":
            raise PipelineError("--shard-index goes with --stage render (an array task of the render)")
        raise PipelineError(f"--shard-index {args.shard_index}: give 0 to --num-shards - 1 ({args.num_shards - 1})")
    if args.submit or args.status:
        slurm.require_sbatch()


def render_supports_family() -> bool:
    """Whether this checkout's ``datagen.render`` takes ``--family`` (added alongside this pipeline)."""
    result = subprocess.run([sys.executable, "-m", "datagen.render", "--help"], capture_output=True, text=True, cwd=ROOT)
    return "--family" in result.stdout


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
        check_cluster_options(args)
        pipeline = Pipeline(args, target)
        try:
            return plan_and_run(args, target, pipeline)
        finally:
            if args.plan_only:
                remove_tree(pipeline.private)

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
    if (args.stage or args.status) and not (pipeline.run / "plan.json").is_file():
        raise PipelineError(f"{pipeline.run} holds no planned run (no plan.json): run the command without "
                            f"{'--stage' if args.stage else '--status'} first (--cluster slurm --submit plans it)")
    pipeline.plan()
    stages = pipeline.stages()
    if args.stage:
        return run_stage(pipeline, stages, args.stage, args.shard_index, args.num_shards)
    if not args.plan_only and (not args.cluster or args.submit):
        repair(pipeline.run, stages, pipeline.sizes.frames)
    if not args.status:
        pipeline.print_plan(stages)
    if args.plan_only:
        return 0
    if args.cluster == "k8s":
        for path in write_manifests(pipeline, args.num_shards):
            print(f"wrote {path}")
        return 0
    if args.cluster == "slurm":
        return on_slurm(pipeline, stages, args)
    pipeline.save_plan()
    # Outside a stage's subprocess (which gets the signal passed on), a SIGTERM ends the run as Ctrl-C does:
    # nothing half-made is recorded as done, and the exit code says which signal stopped it.
    signal.signal(signal.SIGTERM, _stop_by_sigterm)
    try:
        return execute(pipeline, stages)
    except KeyboardInterrupt as stop:
        print(f"stopped: rerun the same command to continue ({pipeline.run} keeps every finished stage)",
              file=sys.stderr)
        return 143 if stop.args == ("SIGTERM",) else 130


def _stop_by_sigterm(signum, frame) -> None:
    raise KeyboardInterrupt("SIGTERM")
