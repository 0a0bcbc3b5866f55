"""The run on SLURM (``--cluster slurm``): each stage a job of ``python -m train.pipeline ... --stage NAME``
(the render stage an array job, task i rendering ``--shard-index i --num-shards K``), with its resources, its
outputs checked by `train.pipeline.checks` and its progress read from the run folder; written to
``OUT/cluster``, submitted and followed with ``--submit`` (`train.cluster.watch`), reported with ``--status``."""

from __future__ import annotations

import argparse
import math
import re
import shlex
import sys
from dataclasses import dataclass
from pathlib import Path

from datagen.shards import list_shards
from train.cluster import slurm
from train.cluster.jobs import Job, write_script
from train.cluster.watch import Tracker, follow
from train.pipeline.checks import checkpoint_step, is_done
from train.pipeline.plan import PipelineError, Stage
from train.pipeline.records import slug
from train.pipeline.run import settle_render
from train.pipeline.stages import Pipeline

# Memory asked for when --mem is not given (MB): Blender with a scene, a trainer with its loader workers, the rest.
DEFAULT_MEM_MB = {"render": 4096, "trainer": 16384, "other": 8192}
DEFAULT_CPUS = 4


@dataclass(frozen=True)
class Options:
    """The cluster options of the command line, parsed: None where the plan decides."""

    partition: str | None
    cpus: int | None
    mem_mb: int | None
    gpus: int | None
    minutes: int | None
    max_retries: int
    poll: float


def parse_memory(text: str) -> int:
    """"16G", "8000M", "8000" (MB), "1T" -> MB, as sbatch --mem reads them."""
    match = re.fullmatch(r"\s*(\d+)\s*([KMGT]?)B?\s*", text.upper())
    if not match or int(match[1]) < 1:
        raise PipelineError(f"--mem {text!r}: give memory per job as sbatch takes it, e.g. 16G or 8000M")
    factor = {"K": 1 / 1024, "": 1, "M": 1, "G": 1024, "T": 1024 * 1024}[match[2]]
    return max(1, math.ceil(int(match[1]) * factor))


def options_of(args: argparse.Namespace) -> Options:
    if args.cpus_per_task is not None and args.cpus_per_task < 1:
        raise PipelineError(f"--cpus-per-task {args.cpus_per_task}: give 1 or more")
    if args.gpus is not None and args.gpus < 0:
        raise PipelineError(f"--gpus {args.gpus}: give 0 or more GPUs per trainer job")
    if args.max_retries < 0 or args.poll <= 0:
        raise PipelineError("--max-retries must be >= 0 and --poll > 0 seconds")
    minutes = None
    if args.time is not None:
        try:
            minutes = slurm.parse_minutes(args.time)
        except slurm.ClusterError as error:
            raise PipelineError(f"--time {args.time!r}: give minutes, HH:MM:SS or D-HH:MM:SS") from error
        if not minutes:
            raise PipelineError(f"--time {args.time!r}: give a positive time limit per job")
    return Options(args.partition, args.cpus_per_task, parse_memory(args.mem) if args.mem else None, args.gpus,
                   minutes, args.max_retries, args.poll)


def trainer_gpus(pipeline: Pipeline, options: Options) -> int:
    """GPUs per trainer job: --gpus, else --nproc-per-node with --device cuda, else none."""
    if options.gpus is not None:
        return options.gpus
    return pipeline.args.nproc_per_node if pipeline.args.device.startswith("cuda") else 0


def stage_command(pipeline: Pipeline, stage: Stage, options: Options, extra: list[str] = ()) -> list[str]:
    """The job's command: this run's pipeline (its reproduce command, with absolute paths: the run folder, its
    saved board file, --init) limited to ``stage``."""
    parts = shlex.split(pipeline.reproduce_command())
    parts[0:1] = [sys.executable]
    absolute = {"--out": str(pipeline.run.resolve())}
    if pipeline.target.board is not None:
        absolute["--board"] = str(pipeline.board_file().resolve())
    if Path(parts[parts.index("--init") + 1]).is_file():
        absolute["--init"] = str(Path(parts[parts.index("--init") + 1]).resolve())
    for option, value in absolute.items():
        parts[parts.index(option) + 1] = value
    gpus = trainer_gpus(pipeline, options)
    parts += ["--device", pipeline.args.device, "--nproc-per-node", str(max(1, gpus)), "--workers",
              str(pipeline.args.workers), "--quiet", "--stage", stage.name, *extra]
    return parts


def resources(pipeline: Pipeline, stage: Stage, options: Options, partition: slurm.Partition | None,
              tasks: int) -> slurm.Resources:
    """A stage's resources: the flags where given (checked against the partition by the caller), else the
    plan's (twice its ETA and 10 minutes; memory and CPUs by kind of stage) cut to what the partition offers."""
    trainer = stage.folder is not None
    kind = "render" if stage.name == "render" else "trainer" if trainer else "other"
    cpus = options.cpus or (min(DEFAULT_CPUS, partition.cpus) if partition else DEFAULT_CPUS)
    mem = options.mem_mb or (min(DEFAULT_MEM_MB[kind], partition.mem_mb) if partition and partition.mem_mb
                             else DEFAULT_MEM_MB[kind])
    eta = stage.eta / tasks if tasks else stage.eta
    minutes = options.minutes or max(15, math.ceil((2 * eta + 600) / 60))
    if options.minutes is None and partition and partition.max_minutes:
        minutes = min(minutes, partition.max_minutes)
    return slurm.Resources(cpus=cpus, mem_mb=mem, gpus=trainer_gpus(pipeline, options) if trainer else 0,
                           minutes=minutes)


def render_tasks(pipeline: Pipeline, num_shards: int) -> tuple[int, int]:
    """(array tasks, shards of the render): no more tasks than shards."""
    shards = -(-pipeline.sizes.frames // pipeline.render_shard_size)
    return min(num_shards, shards), shards


def slurm_jobs(pipeline: Pipeline, stages: list[Stage], options: Options, partition: slurm.Partition | None,
               num_shards: int) -> list[Job]:
    """The jobs of the stages, in order; the render stage an array over its shards."""
    run, frames = pipeline.run, pipeline.sizes.frames
    jobs = []
    for stage in stages:
        def done(stage=stage) -> bool:
            return settle_render(pipeline, stage) or is_done(run, stage, frames)

        if stage.name == "render":
            tasks, shards = render_tasks(pipeline, num_shards)
            renders = run / "data" / "renders"

            def present(renders=renders) -> set[int]:
                return {int(p.stem.split("-")[1]) for p in list_shards(renders)} if renders.is_dir() else set()

            def task_done(i: int, tasks=tasks, shards=shards, present=present) -> bool:
                return set(range(i, shards, tasks)) <= present()

            jobs.append(Job(stage.name, stage_command(pipeline, stage, options, [
                "--shard-index", "$SLURM_ARRAY_TASK_ID", "--num-shards", str(tasks)]),
                resources(pipeline, stage, options, partition, tasks), done, tasks=tasks, task_done=task_done,
                progress=lambda shards=shards, present=present: f"{len(present())}/{shards} shards"))
            continue
        progress = (lambda stage=stage: f"step {checkpoint_step(stage.folder / 'last.pt')} of {stage.steps}"
                    ) if stage.folder is not None else (lambda: "")
        jobs.append(Job(slug(stage.name), stage_command(pipeline, stage, options),
                        resources(pipeline, stage, options, partition, 0), done, progress=progress))
    return jobs


def tracker(pipeline: Pipeline, stages: list[Stage], options: Options, partition: slurm.Partition | None,
            num_shards: int) -> Tracker:
    run = pipeline.run.resolve()
    return Tracker(slurm_jobs(pipeline, stages, options, partition, num_shards), run / "cluster", run,
                   slug(run.name) or "run", partition, options.max_retries)


def on_slurm(pipeline: Pipeline, stages: list[Stage], args: argparse.Namespace) -> int:
    """``--cluster slurm``: write the job scripts; ``--submit`` them (and follow them unless ``--no-wait``);
    ``--status``: say where each stage stands. What the cluster cannot give is refused before anything is
    written."""
    options = options_of(args)
    partition = slurm.choose_partition(options.partition) if args.submit or args.status else None
    follow_up = tracker(pipeline, stages, options, partition, args.num_shards)
    if args.status:
        for _, line in follow_up.lines():
            print(line)
        return 0
    if partition is not None:
        for job in follow_up.jobs:
            slurm.check_fits(partition, job.resources, job.name)
    pipeline.save_plan()  # the jobs plan from it: the sizes fixed here
    for job in follow_up.jobs:  # this plan's scripts with these options (a job resubmitted later runs them)
        path = write_script(job, follow_up.folder, chdir=follow_up.chdir, partition=partition, tag=follow_up.tag)
        if not args.submit:
            print(f"wrote {path}")
    if not args.submit:
        print("submit them with the same command and --submit: it chains them (the render as an array job), follows "
              "them and resubmits failed ones")
        return 0
    code = follow(follow_up, wait=not args.no_wait, poll=options.poll)
    if code == 0 and not args.no_wait:
        print(f"done: {pipeline.run / 'detector.pt'} (Detector(weights=...), detect --weights); card "
              f"{pipeline.run / 'MODEL_CARD.md'}")
    return code
