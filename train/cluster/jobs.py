"""The jobs of a cluster run and their batch scripts: a `Job` is one stage (one command, or an array of tasks
each running the command with its ``$SLURM_ARRAY_TASK_ID``), with its resources and the checks that say, from
its outputs on the shared disk, whether it (or one task) is done. Scripts are written to the run's ``cluster/``
folder with absolute paths, so that they run from whatever folder the cluster starts them in (``--chdir``)."""

from __future__ import annotations

import shlex
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from deepcharuco.core.files import write_atomic
from train.cluster.slurm import Partition, Resources


@dataclass
class Job:
    """One stage of the run as a SLURM job. ``tasks`` > 0: an array job of tasks 0..tasks-1 and ``task_done(i)``
    says whether task i's outputs are complete; ``done()`` whether the whole stage's are; ``progress()`` a few
    words on how far it got (shards done of K, a trainer's step)."""

    name: str
    command: list[str]  # argv; an item "$SLURM_ARRAY_TASK_ID" / "$SLURM_CPUS_PER_TASK" is left for the shell
    resources: Resources
    done: Callable[[], bool]
    tasks: int = 0
    task_done: Callable[[int], bool] | None = None
    progress: Callable[[], str] = field(default=lambda: "")

    def __post_init__(self) -> None:
        if self.tasks and self.task_done is None:
            raise ValueError(f"array job {self.name} needs task_done")


SHELL_VARIABLES = ("$SLURM_ARRAY_TASK_ID", "$SLURM_CPUS_PER_TASK")


def shell_line(command: list[str]) -> str:
    """``command`` quoted for bash, SLURM's variables left for the shell to fill in."""
    return " ".join(f'"{part}"' if part in SHELL_VARIABLES else shlex.quote(part) for part in command)


def script_path(folder: Path, job: Job) -> Path:
    return folder / f"{job.name}.sbatch"


def write_script(job: Job, folder: Path, *, chdir: Path, partition: Partition | None, tag: str) -> Path:
    """Write ``folder/NAME.sbatch`` for ``job``: its resources as ``#SBATCH`` lines, its log in ``folder/logs``
    (``NAME-JOBID.log``, an array's ``NAME-JOBID_TASK.log``); the array's tasks and the dependencies are given
    on sbatch's command line at submission, as they change when tasks are resubmitted. ``tag`` names the run in
    the job name (squeue's NAME column)."""
    logs = folder / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    log = logs / (f"{job.name}-%A_%a.log" if job.tasks else f"{job.name}-%j.log")
    directives = [f"--job-name=dc-{tag}-{job.name}", f"--chdir={chdir}", f"--output={log}",
                  *job.resources.sbatch_lines()]
    if partition is not None:
        directives.append(f"--partition={partition.name}")
    what = (f"array: task i of --array runs with SLURM_ARRAY_TASK_ID=i, {job.tasks} tasks in all" if job.tasks
            else "one job")
    path = script_path(folder, job)
    write_atomic(path, "#!/bin/bash\n"
                       f"# Stage {job.name} of the run in {chdir} ({what}); submitted by python -m train.pipeline "
                       "--cluster slurm --submit,\n# which adds --array and --dependency=afterok on sbatch's command "
                       "line.\n"
                       + "".join(f"#SBATCH {d}\n" for d in directives)
                       + "set -euo pipefail\n"
                       + f"exec {shell_line(job.command)}\n")
    path.chmod(0o755)
    return path
