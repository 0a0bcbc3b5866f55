"""Submitting, following and recovering a run's jobs on SLURM.

What is done is decided by the outputs on disk (each `Job`'s checks), never by the scheduler's word: a pass
(`Tracker.step`) walks the jobs in order and submits each one, or each array task, that is neither done nor in
the queue, after (``--dependency=afterok``) the jobs of earlier stages still in the queue. A submission replaces
what waited on the jobs it replaces: the later stages' queued jobs are cancelled and submitted again after the
new one. So the first pass submits the whole run, a pass after a failed or preempted task resubmits that task
(at most ``max_retries`` times in one session, saying how the scheduler says it ended), and a pass over a
finished run, or over a run whose jobs are all still queued, submits nothing: a rerun after anything (a
cancelled job, a lost node, the watcher stopped by Ctrl-C) submits only what is missing.

The submitted job IDs are kept in ``cluster/jobs.json`` so that a later command finds the run's jobs in the
queue; ``squeue`` says which are still there, ``scontrol show job`` how the others ended."""

from __future__ import annotations

import datetime as dt
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from train.cluster import slurm
from train.cluster.jobs import Job, script_path, write_script
from deepcharuco.core.files import write_atomic


# squeue's reasons of a pending job that no wait will change (sbatch accepts such a job and it waits for ever).
NEVER_STARTS = {"PartitionConfig", "PartitionTimeLimit", "PartitionNodeLimit", "BadConstraints", "InvalidQOS",
                "InvalidAccount", "QOSMaxCpuPerJobLimit", "QOSMaxGRESPerJob", "QOSMaxMemoryPerJob",
                "QOSMaxWallDurationPerJobLimit"}


class StageFailed(Exception):
    """A stage (or array task) failed more often than ``max_retries`` allows: the message says how and where
    its log is."""


@dataclass
class Tracker:
    """The jobs of one run, the folder of their scripts, logs and ``jobs.json``, and the retries left."""

    jobs: list[Job]
    folder: Path
    chdir: Path
    tag: str
    partition: slurm.Partition | None
    max_retries: int = 2
    say: Callable[[str], None] = field(default=lambda line: print(line, flush=True))
    attempts: dict = field(default_factory=dict)  # (job name, task or None) -> submissions in this session
    shown: dict = field(default_factory=dict)  # job name -> its last progress line
    finished: set = field(default_factory=set)  # jobs found done in this session (their checks read every file)

    # -- the record of submissions
    @property
    def record_path(self) -> Path:
        return self.folder / "jobs.json"

    def submissions(self) -> list[dict]:
        try:
            record = json.loads(self.record_path.read_text())
        except (OSError, ValueError):  # none yet, or cut off: the queue's jobs of the run are then unknown
            return []
        return record.get("submissions", []) if isinstance(record, dict) else []

    def remember(self, job: Job, job_id: str, tasks: list[int] | None, after: list[str]) -> None:
        stamp = dt.datetime.now(dt.timezone.utc).replace(microsecond=0).isoformat()
        submissions = self.submissions() + [{"job": job.name, "id": job_id, "tasks": tasks, "after": after,
                                             "submitted": stamp}]
        self.folder.mkdir(parents=True, exist_ok=True)
        write_atomic(self.record_path, json.dumps({"submissions": submissions}, indent=1) + "\n")

    def queued(self) -> dict[str, dict]:
        """The run's jobs in the queue: ``{job name: {task or None: [(slurm id, state, reason)]}}``."""
        by_id = {s["id"]: s for s in self.submissions()}
        found: dict[str, dict] = {}
        for slurm_id, (state, reason) in slurm.queue(list(by_id)).items():
            base, _, task = slurm_id.partition("_")
            index = int(task) if task.isdigit() else None
            found.setdefault(by_id[base]["job"], {}).setdefault(index, []).append((slurm_id, state, reason))
        return found

    def done(self, job: Job) -> bool:
        """``job.done()``, asked until it says yes: its checks read every output (shards, checkpoints)."""
        if job.name not in self.finished and job.done():
            self.finished.add(job.name)
        return job.name in self.finished

    # -- one pass
    def step(self) -> bool:
        """Submit what is neither done nor queued (see the module's docstring); True when every job is done.
        Raises `StageFailed` when a job must be submitted again and its retries are spent."""
        queued = self.queued()
        upstream: list[str] = []  # the queued and new jobs of earlier stages not done
        replaced = False
        for position, job in enumerate(self.jobs):
            if self.done(job):
                continue
            mine = queued.get(job.name, {})
            if replaced and mine:  # they wait on jobs just replaced: submitted again after the new ones
                ids = [entry[0] for entries in mine.values() for entry in entries]
                slurm.cancel(ids)
                self.say(f"{job.name}: cancelled {', '.join(ids)} (it waited on replaced jobs): submitted again")
                mine = {}
            stuck = [(i, r) for entries in mine.values() for i, state, r in entries if r in NEVER_STARTS]
            if stuck:
                slurm.cancel(queued_ids(queued, self.jobs[position:]))
                raise StageFailed(f"{job.name}: job {stuck[0][0]} can never start (SLURM says {stuck[0][1]}): "
                                  f"cancelled it and the jobs after it; ask for resources the partition gives "
                                  f"(sinfo -o '%P %c %m %G %l'), then rerun")
            if job.tasks:
                todo = [i for i in range(job.tasks) if i not in mine and not job.task_done(i)]
            else:
                todo = [] if mine else [None]
            new: list[str] = []
            if todo:
                try:
                    self.count(job, todo)
                except StageFailed:  # the later stages' jobs would wait for ever on this one
                    slurm.cancel(queued_ids(queued, self.jobs[position + 1:]))
                    raise
                script = script_path(self.folder, job)
                if not script.is_file():
                    write_script(job, self.folder, chdir=self.chdir, partition=self.partition, tag=self.tag)
                tasks = todo if job.tasks else None
                job_id = slurm.submit(script, array=tasks, after=upstream)
                self.remember(job, job_id, tasks, upstream)
                new = [f"{job_id}_{i}" for i in todo] if job.tasks else [job_id]
                waits = f" after {', '.join(upstream)}" if upstream else ""
                self.say(f"{job.name}: submitted job {job_id}"
                         + (f" (tasks {','.join(map(str, todo))} of {job.tasks})" if job.tasks else "") + waits)
                replaced = True
            upstream += [entry[0] for entries in mine.values() for entry in entries] + new
        return all(self.done(job) for job in self.jobs)

    def count(self, job: Job, todo: list) -> None:
        """Count a (re)submission of ``todo`` (array tasks, or [None]); say how the last one ended; raise
        `StageFailed` past ``max_retries`` resubmissions in this session."""
        for task in todo:
            key = (job.name, task)
            previous = self.last_submission(job, task)
            self.attempts[key] = self.attempts.get(key, 0) + 1
            if previous is None:
                continue
            slurm_id = previous if task is None else f"{previous}_{task}"
            how = next((e.describe() for e in slurm.ended(previous) if e.job_id in (slurm_id, previous)),
                       "gone from the queue (the controller no longer knows how it ended)")
            what = job.name if task is None else f"{job.name} task {task}"
            log = self.folder / "logs" / (f"{job.name}-{previous}_{task}.log" if task is not None
                                          else f"{job.name}-{previous}.log")
            retry = self.attempts[key] - 1
            if retry > self.max_retries:
                raise StageFailed(f"{what} (job {slurm_id}) ended {how} and its outputs are not complete, after "
                                  f"{self.max_retries} resubmission(s): see {log}; fix what it says and rerun the "
                                  f"same command (finished work is kept)")
            self.say(f"{what}: job {slurm_id} ended {how} before its outputs were complete: "
                     + (f"resubmitted (retry {retry} of {self.max_retries})" if retry else "submitted again"))

    def last_submission(self, job: Job, task: int | None) -> str | None:
        for entry in reversed(self.submissions()):
            if entry["job"] == job.name and (task is None or task in (entry.get("tasks") or [])):
                return entry["id"]
        return None

    # -- reporting
    def lines(self) -> list[tuple[str, str]]:
        """(job name, one line on where it stands) for every job."""
        queued = self.queued()
        result = []
        for job in self.jobs:
            if self.done(job):
                result.append((job.name, f"{job.name}: done"))
                continue
            entries = [e for es in queued.get(job.name, {}).values() for e in es]
            states = ", ".join(f"{i} {s}" + (f" ({r})" if r not in ("None", "") else "") for i, s, r in entries)
            progress = job.progress()
            submitted = any(s["job"] == job.name for s in self.submissions())
            where = states or ("not in the queue" if submitted else "not submitted")
            result.append((job.name, f"{job.name}: {progress + '; ' if progress else ''}{where}"))
        return result

    def report(self) -> None:
        """Print each job's line when it changed since the last report (a progress line per stage)."""
        for name, line in self.lines():
            if self.shown.get(name) != line:
                self.shown[name] = line
                self.say(f"[{time.strftime('%H:%M:%S')}] {line}")


def queued_ids(queued: dict[str, dict], jobs: list[Job]) -> list[str]:
    """The SLURM IDs in ``queued`` (`Tracker.queued`) of ``jobs``."""
    return [entry[0] for job in jobs for entries in queued.get(job.name, {}).values() for entry in entries]


def follow(tracker: Tracker, *, wait: bool, poll: float) -> int:
    """Submit what is missing, then (``wait``) follow the jobs until every one is done (0) or a stage failed for
    good (1); without ``wait``, return after submitting (0). Ctrl-C stops the watching, never the jobs."""
    try:
        while True:
            try:
                finished = tracker.step()
            except StageFailed as failure:
                tracker.report()
                print(f"error: {failure}", file=sys.stderr)
                return 1
            if finished:
                tracker.report()
                return 0
            if not wait:
                queued = tracker.queued()
                ids = sorted({e[0].split("_")[0] for jobs in queued.values() for es in jobs.values() for e in es},
                             key=int)
                print(f"submitted; the run's jobs in the queue: {' '.join(ids) or 'none'} (follow them: the same "
                      f"command without --no-wait, or with --status)", flush=True)
                return 0
            tracker.report()
            time.sleep(poll)
    except KeyboardInterrupt:
        raise KeyboardInterrupt("stopped watching; the jobs keep running on the cluster: rerun the same command to "
                                "follow them again (it submits only what is missing)") from None
