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
from train.pipeline.cluster import write_cluster_scripts
from train.pipeline.plan import MIN_EVAL_SEQUENCES, ROOT, PipelineError, Target, check_target, parse_duration
from train.pipeline.records import remove_tree
from train.pipeline.run import execute
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
    cluster = parser.add_argument_group("cluster")
    cluster.add_argument("--cluster", choices=("slurm", "k8s"), default=None,
                         help="write (not submit) a render array job and a training job for this plan, then stop")
    cluster.add_argument("--num-shards", type=int, default=16, help="--cluster: render jobs in the array")
    parser.add_argument("--plan-only", action="store_true", help="print the plan and its ETA, run nothing")
    parser.add_argument("--quiet", action="store_true", help="no progress bars from the stages")
    return parser


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
    pipeline.plan()
    stages = pipeline.stages()
    if not args.plan_only and not args.cluster:
        repair(pipeline.run, stages, pipeline.sizes.frames)
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
        return execute(pipeline, stages)
    except KeyboardInterrupt as stop:
        print(f"stopped: rerun the same command to continue ({pipeline.run} keeps every finished stage)",
              file=sys.stderr)
        return 143 if stop.args == ("SIGTERM",) else 130


def _stop_by_sigterm(signum, frame) -> None:
    raise KeyboardInterrupt("SIGTERM")
