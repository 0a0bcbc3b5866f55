"""SLURM's commands as functions: what the cluster offers (``sinfo``), submitting a batch script (``sbatch
--parsable``, with ``--array`` and ``--dependency=afterok``), the jobs in the queue (``squeue -r``: one line per
array task), how a job ended (``scontrol show job``: finished jobs stay there ``MinJobAge`` seconds, 300 by default;
``sacct`` is left out, since a small cluster keeps no accounting) and cancelling (``scancel``).

Job IDs are SLURM's strings: ``"12"`` for a job, ``"12_3"`` for task 3 of array job 12."""

from __future__ import annotations

import re
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

from deepcharuco.core.errors import DeepCharucoError

# squeue's states of a job that is still to run or running (the others have left the queue or are leaving it).
ALIVE = {"PENDING", "CONFIGURING", "RUNNING", "COMPLETING", "SUSPENDED", "REQUEUED", "REQUEUE_HOLD", "REQUEUE_FED",
         "RESIZING", "SIGNALING", "STAGE_OUT", "STOPPED"}


class ClusterError(DeepCharucoError):
    """The cluster cannot do what was asked (no sbatch, an unknown partition, resources it lacks): one line."""


@dataclass(frozen=True)
class Resources:
    """What one job (or each task of an array) asks for. ``mem_mb`` 0: the cluster's default."""

    cpus: int
    mem_mb: int
    gpus: int
    minutes: int

    def sbatch_lines(self) -> list[str]:
        lines = [f"--cpus-per-task={self.cpus}", f"--time={self.minutes // 60}:{self.minutes % 60:02d}:00"]
        if self.mem_mb:
            lines.append(f"--mem={self.mem_mb}M")
        if self.gpus:
            lines.append(f"--gres=gpu:{self.gpus}")
        return lines


@dataclass(frozen=True)
class Partition:
    """A partition as ``sinfo`` reports it: the most any of its nodes has (CPUs, memory, GPUs) and its time limit
    (None: no limit)."""

    name: str
    default: bool
    cpus: int
    mem_mb: int
    gpus: int
    max_minutes: int | None


@dataclass(frozen=True)
class Ended:
    """How a job or array task ended, as ``scontrol`` says (state, reason, exit code), or "unknown" once the
    controller has forgotten it."""

    job_id: str
    state: str
    reason: str
    exit_code: str

    def describe(self) -> str:
        reason = "" if self.reason in ("None", "") else f", reason {self.reason}"
        return f"{self.state} (exit code {self.exit_code}{reason})"


def require_sbatch() -> None:
    if shutil.which("sbatch") is None or shutil.which("squeue") is None:
        raise ClusterError("--submit needs SLURM's sbatch and squeue on the PATH: run it on the cluster's login node "
                           "(or start a one-node cluster here with scripts/local_slurm.sh), or leave --submit out to "
                           "only write the job scripts")


def _run(command: list[str]) -> str:
    """stdout of a SLURM command; its failure is a `ClusterError` with SLURM's own message."""
    try:
        result = subprocess.run(command, capture_output=True, text=True, timeout=120)
    except FileNotFoundError as error:
        raise ClusterError(f"{command[0]} is not on the PATH ({error.strerror}): run this on the cluster's login "
                           f"node") from None
    except subprocess.TimeoutExpired:
        raise ClusterError(f"{command[0]} did not answer in 120 s: is slurmctld up? (scontrol ping)") from None
    if result.returncode != 0:
        message = " ".join(result.stderr.split()) or f"exit code {result.returncode}"
        raise ClusterError(f"{' '.join(command[:2])} failed: {message}")
    return result.stdout


def parse_minutes(text: str) -> int | None:
    """SLURM's time (``MM``, ``MM:SS``, ``HH:MM:SS``, ``D-HH[:MM[:SS]]``) in whole minutes, rounded up; None for
    ``infinite``/``UNLIMITED``. Anything else is a `ClusterError`."""
    text = text.strip()
    if text.lower() in ("infinite", "unlimited"):
        return None
    match = re.fullmatch(r"(?:(\d+)-)?(\d+)(?::(\d+))?(?::(\d+))?", text)
    if not match:
        raise ClusterError(f"time {text!r}: give minutes, HH:MM:SS or D-HH:MM:SS, as sbatch --time takes")
    days, first, second, third = (int(g) if g else None for g in match.groups())
    if days is not None:  # D-HH[:MM[:SS]]
        seconds = days * 86400 + first * 3600 + (second or 0) * 60 + (third or 0)
    elif third is not None:  # HH:MM:SS
        seconds = first * 3600 + second * 60 + third
    elif second is not None:  # MM:SS
        seconds = first * 60 + second
    else:  # MM
        seconds = first * 60
    return -(-seconds // 60)


def partitions() -> dict[str, Partition]:
    """The cluster's partitions by name (``sinfo``), each with the most its nodes offer."""
    found: dict[str, Partition] = {}
    for line in _run(["sinfo", "-h", "-o", "%P|%c|%m|%G|%l"]).splitlines():
        if not line.strip():
            continue
        name, cpus, mem, gres, limit = line.split("|")
        default = name.endswith("*")
        name = name.rstrip("*")
        gpus = sum(int(m[1]) for m in re.finditer(r"gpu(?::[^:,(]+)?:(\d+)", gres))
        partition = Partition(name, default, int(cpus.rstrip("+")), int(re.sub(r"\D", "", mem) or 0), gpus,
                              parse_minutes(limit))
        if name in found:  # nodes of several shapes: the most any one of them has
            old = found[name]
            partition = Partition(name, default or old.default, max(old.cpus, partition.cpus),
                                  max(old.mem_mb, partition.mem_mb), max(old.gpus, partition.gpus), partition.max_minutes)
        found[name] = partition
    return found


def choose_partition(name: str | None) -> Partition:
    """``--partition`` as the cluster knows it (the default partition when None); an unknown name is refused."""
    known = partitions()
    if not known:
        raise ClusterError("sinfo lists no partition: the cluster has no nodes to run on (ask its administrator)")
    if name is None:
        default = [p for p in known.values() if p.default] or list(known.values())
        return default[0]
    if name not in known:
        raise ClusterError(f"--partition {name}: the cluster has no such partition (sinfo lists: "
                           f"{', '.join(sorted(known))}): give one of those")
    return known[name]


def check_fits(partition: Partition, resources: Resources, what: str) -> None:
    """Refuse resources no node of ``partition`` has (the job would wait forever, or sbatch refuses it later)."""
    problems = []
    if resources.cpus > partition.cpus:
        problems.append(f"{resources.cpus} CPUs (--cpus-per-task), its nodes have at most {partition.cpus}")
    if resources.mem_mb > partition.mem_mb > 0:
        problems.append(f"{resources.mem_mb} MB of memory (--mem), its nodes have at most {partition.mem_mb} MB")
    if resources.gpus > partition.gpus:
        problems.append(f"{resources.gpus} GPU(s) (--gpus), its nodes have {partition.gpus or 'none'}")
    if partition.max_minutes is not None and resources.minutes > partition.max_minutes:
        problems.append(f"{resources.minutes} minutes (--time), its limit is {partition.max_minutes}")
    if problems:
        raise ClusterError(f"the {what} job asks partition {partition.name} for {'; '.join(problems)}: ask for less, "
                           f"or choose another --partition")


def submit(script: Path, *, array: list[int] | None = None, after: list[str] = ()) -> str:
    """Submit ``script``; its job ID. ``array``: the tasks to run (``--array``); ``after``: job IDs that must end
    well first (``--dependency=afterok``)."""
    command = ["sbatch", "--parsable"]
    if array:
        command.append("--array=" + ",".join(str(i) for i in array))
    if after:
        command.append("--dependency=afterok:" + ":".join(after))
    job = _run([*command, str(script)]).strip().split(";")[0]  # "ID" or "ID;cluster"
    if not job.isdigit():
        raise ClusterError(f"sbatch answered {job!r} instead of a job ID")
    return job


def queue(job_ids: list[str]) -> dict[str, tuple[str, str]]:
    """The jobs of ``job_ids`` (base IDs) still in the queue: ``{id or id_task: (state, reason)}``, one entry per
    array task (``squeue -r``). Jobs the controller no longer knows are left out."""
    if not job_ids:
        return {}
    # squeue refuses the whole list when one job has been forgotten: ask for every job and keep ours.
    lines = _run(["squeue", "-h", "-r", "-o", "%i|%T|%r"]).splitlines()
    wanted = set(job_ids)
    found = {}
    for line in lines:
        job, state, reason = (line.split("|") + ["", ""])[:3]
        if job.split("_")[0] in wanted and state in ALIVE:
            found[job] = (state, reason)
    return found


def ended(job_id: str) -> list[Ended]:
    """How ``job_id`` (a job or an array: one entry per task) ended, from ``scontrol show job``; an empty list
    once the controller has forgotten it."""
    try:
        text = _run(["scontrol", "-o", "show", "job", job_id])
    except ClusterError:
        return []
    result = []
    for line in text.splitlines():
        fields = dict(part.split("=", 1) for part in line.split() if "=" in part)
        task = fields.get("ArrayTaskId")
        name = f"{fields.get('ArrayJobId', job_id)}_{task}" if task and task.isdigit() else fields.get("JobId", job_id)
        result.append(Ended(name, fields.get("JobState", "unknown"), fields.get("Reason", ""),
                            fields.get("ExitCode", "?")))
    return result


def cancel(job_ids: list[str]) -> None:
    if job_ids:
        subprocess.run(["scancel", *job_ids], capture_output=True, text=True, timeout=120)
