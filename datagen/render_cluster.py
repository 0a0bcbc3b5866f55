"""``python -m datagen.render ... --num-shards K --cluster slurm --submit``: a bare render as a SLURM array job of K
tasks, task i rendering ``--shard-index i --num-shards K`` into the shared ``--out``, followed until every shard
is there; a failed or preempted task is resubmitted (`train.cluster.watch`). Scripts, logs and ``jobs.json`` go
to ``OUT/cluster``."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from datagen.shards import list_shards, update_index
from deepcharuco.core.errors import DeepCharucoError

ASSUMED_S_PER_FRAME = 0.54  # 320x240 on an idle core, docs/rendering.md; the default --time is twice that + 10 min
RENDER_MEM_MB = 4096


def add_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("cluster (docs/training.md, On a cluster)")
    group.add_argument("--cluster", choices=("slurm",), default=None,
                       help="render as a SLURM array job of --num-shards tasks (needs --submit)")
    group.add_argument("--submit", action="store_true", help="--cluster slurm: submit the tasks whose shards are "
                                                             "missing and follow them, resubmitting failed ones")
    group.add_argument("--no-wait", action="store_true", help="--submit: exit after submitting, with the job ID")
    group.add_argument("--partition", default=None, help="SLURM partition (default: the cluster's default)")
    group.add_argument("--cpus-per-task", type=int, default=None, help="CPUs per task (default: 4, or the nodes' "
                                                                      "CPUs if fewer): Cycles threads")
    group.add_argument("--time", default=None, help="time limit per task (default: twice the frames' estimate + 10 min)")
    group.add_argument("--max-retries", type=int, default=2, help="times a failed task is resubmitted")
    group.add_argument("--poll", type=float, default=10.0, help="seconds between looks at the queue")


def task_command(args: argparse.Namespace) -> list[str]:
    """What each task runs: this render with absolute paths, its own shards, the job's CPUs as Cycles threads."""
    command = [sys.executable, "-m", "datagen.render", "--n", str(args.n), "--out", str(Path(args.out).resolve()),
               "--seed", str(args.seed), "--width", str(args.width), "--height", str(args.height),
               "--shard-size", str(args.shard_size), "--device", args.device, "--recycle", str(args.recycle)]
    if args.board is not None:
        command += ["--board", str(Path(args.board).resolve())]
    if args.family is not None:
        command += ["--family", args.family]
    for option in ("samples", "distortion_probability", "shadow_probability"):
        if getattr(args, option) is not None:
            command += [f"--{option.replace('_', '-')}", str(getattr(args, option))]
    if args.clean:
        command.append("--clean")
    return command + ["--shard-index", "$SLURM_ARRAY_TASK_ID", "--num-shards", str(args.num_shards),
                      "--threads", "$SLURM_CPUS_PER_TASK", "--resume", "--quiet"]


def submit_render(args: argparse.Namespace) -> int:
    """Submit the tasks with missing shards (``args``: datagen.render's, checked) and follow them (0: every shard
    is there, 1: a task failed past its retries)."""
    # Imported here: train/ needs torch, which a render-only install (the render extra) does not have.
    from train.cluster import slurm
    from train.cluster.jobs import Job, write_script
    from train.cluster.watch import Tracker, follow

    if not args.cluster:
        raise DeepCharucoError("--submit goes with --cluster slurm (and --num-shards K for K array tasks)")
    if not args.submit:
        raise DeepCharucoError("--cluster slurm renders through the scheduler: add --submit (and --num-shards K "
                               "for K array tasks)")
    if args.cpus_per_task is not None and args.cpus_per_task < 1 or args.max_retries < 0 or args.poll <= 0:
        raise DeepCharucoError("--cpus-per-task must be >= 1, --max-retries >= 0, --poll > 0")
    slurm.require_sbatch()
    partition = slurm.choose_partition(args.partition)
    out = Path(args.out).resolve()
    shards = -(-args.n // args.shard_size)
    tasks = min(args.num_shards, shards)
    if tasks < args.num_shards:
        raise slurm.ClusterError(f"--num-shards {args.num_shards}: the run has {shards} shard(s) of --shard-size "
                                 f"{args.shard_size}: give at most {shards} tasks, or a smaller --shard-size")
    minutes = slurm.parse_minutes(args.time) if args.time else max(15, math.ceil(
        (2 * ASSUMED_S_PER_FRAME * args.n / tasks + 600) / 60))
    if args.time is None and partition.max_minutes:
        minutes = min(minutes, partition.max_minutes)
    resources = slurm.Resources(cpus=args.cpus_per_task or min(4, partition.cpus),
                                mem_mb=min(RENDER_MEM_MB, partition.mem_mb or RENDER_MEM_MB), gpus=0, minutes=minutes)
    slurm.check_fits(partition, resources, "render")

    def present() -> set[int]:
        return {int(p.stem.split("-")[1]) for p in list_shards(out)} if out.is_dir() else set()

    def done() -> bool:
        if len(present()) < shards:
            return False
        update_index(out)  # the tasks rewrote it concurrently, each from what it saw
        return True

    job = Job("render", task_command(args), resources, done, tasks=tasks,
              task_done=lambda i: set(range(i, shards, tasks)) <= present(),
              progress=lambda: f"{len(present())}/{shards} shards")
    tracker = Tracker([job], out / "cluster", out, out.name or "render", partition, args.max_retries)
    write_script(job, tracker.folder, chdir=out, partition=partition, tag=tracker.tag)
    code = follow(tracker, wait=not args.no_wait, poll=args.poll)
    if code == 0 and not args.no_wait:
        print(f"datagen.render: {shards} shard(s) in {out} (rendered by {tasks} array tasks)", file=sys.stderr)
    return code
