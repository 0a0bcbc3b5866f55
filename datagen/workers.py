"""Render tasks in local worker processes behind one progress bar.

Blender keeps state between renders and grows in memory, prints a line per render on the C
stdout, and is imported once per process: so renders run in ``spawn``-ed worker processes
(replaced every few tasks), with their stdout silenced. A task is a picklable module-level
function and its arguments.

The parent hands each worker one task at a time over the worker's own pipe and watches the
process itself, so a worker that dies (the out-of-memory killer's ``kill -9``, a crash in
Blender) is noticed at once and named, instead of leaving the parent waiting for a result that
will never come (what ``multiprocessing.Pool`` does). A failed or dead worker ends the run:
the other workers are stopped; what had completed stays.
"""

from __future__ import annotations

import multiprocessing as mp
import multiprocessing.connection
import os
import pickle
import signal
import traceback
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable

from tqdm import tqdm

from deepcharuco.core.errors import DeepCharucoError

_CONNECTION: "mp.connection.Connection | None" = None
_POLL_S = 1.0  # how often the parent looks at its workers when none has anything to say
_STOP_GRACE_S = 5.0  # how long stopped workers get to exit before they are killed


class TaskError(DeepCharucoError):
    """A task that did not complete: its worker raised ``error`` (with the worker's ``traceback``
    text) or died with ``exitcode`` (negative: killed by that signal)."""

    def __init__(self, message: str, task_index: int, error: BaseException | None = None,
                 exitcode: int | None = None, traceback_text: str = ""):
        super().__init__(message)
        self.task_index, self.error, self.exitcode, self.traceback = task_index, error, exitcode, traceback_text


def report_progress(units: int = 1) -> None:
    """Advance the parent's progress bar by ``units`` (a no-op outside a `run_tasks` worker)."""
    if _CONNECTION is not None:
        _CONNECTION.send(("progress", units))


def death_cause(exitcode: int | None) -> str:
    """How a worker process ended, in words (with the likely reason for a SIGKILL)."""
    if exitcode is None:
        return "still running"
    if exitcode < 0:
        name = signal.Signals(-exitcode).name if -exitcode in signal.Signals._value2member_map_ else str(-exitcode)
        hints = {signal.SIGKILL: " (the out-of-memory killer sends it: try fewer --workers or a smaller --recycle)",
                 signal.SIGSEGV: " (a crash: Blender crashes so when its scratch space, /dev/shm or TMPDIR, is full)"}
        return f"killed by {name}{hints.get(-exitcode, '')}"
    return f"exited with code {exitcode}"


def _worker(connection: "mp.connection.Connection", function: Callable[..., Any], limit: int | None) -> None:
    """A worker's life: run the tasks the parent sends until it sends None or ``limit`` are done."""
    global _CONNECTION
    _CONNECTION = connection
    # Blender prints a line per render on the C stdout; keep the parent's progress bar readable.
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    done = 0
    while limit is None or done < limit:
        try:
            message = connection.recv()
        except EOFError:  # the parent is gone
            return
        if message is None:
            return
        index, task = message
        try:
            result = function(*task)
        except KeyboardInterrupt:  # Ctrl-C reaches the whole process group: the parent reports it
            return
        except Exception as error:
            try:
                pickle.loads(pickle.dumps(error))
            except Exception:  # an exception that cannot cross processes: keep its text
                error = RuntimeError(f"{type(error).__name__}: {error}")
            connection.send(("error", index, error, traceback.format_exc()))
            return
        connection.send(("done", index, result))
        done += 1


@dataclass
class _Worker:
    process: mp.Process
    connection: "mp.connection.Connection"
    task: int | None = None  # the index of the task it holds
    done: int = 0


def run_tasks(function: Callable[..., Any], tasks: list[tuple], *, total: int, unit: str, workers: int = 1,
              tasks_per_child: int | None = None, quiet: bool = False) -> list[Any]:
    """``function(*task)`` for every task in ``workers`` processes; returns the results in task order.

    ``total``: progress units that the tasks will report with `report_progress` (the bar's ETA
    is as good as this estimate). A task that raises, or whose worker dies, raises `TaskError`
    here as soon as it happens, after stopping the other workers; KeyboardInterrupt stops the
    workers and is re-raised. Whatever the tasks had completed stays.
    """
    if not tasks:
        return []
    context = mp.get_context("spawn")
    pending = deque(range(len(tasks)))
    results: dict[int, Any] = {}
    running: list[_Worker] = []

    def hand_out(worker: _Worker) -> None:
        if pending and (tasks_per_child is None or worker.done < tasks_per_child):
            worker.task = pending.popleft()
            worker.connection.send((worker.task, tasks[worker.task]))
        else:
            worker.task = None
            if tasks_per_child is None or worker.done < tasks_per_child:
                worker.connection.send(None)  # nothing left: let it exit

    try:
        with tqdm(total=total, unit=unit, disable=quiet, smoothing=0.1) as bar:
            while pending or any(w.task is not None for w in running):
                while pending and len(running) < workers:
                    mine, theirs = context.Pipe()
                    process = context.Process(target=_worker, args=(theirs, function, tasks_per_child), daemon=True)
                    process.start()
                    theirs.close()
                    running.append(worker := _Worker(process, mine))
                    hand_out(worker)
                mp.connection.wait([w.connection for w in running] + [w.process.sentinel for w in running],
                                   timeout=_POLL_S)
                for worker in list(running):
                    _receive(worker, results, bar, hand_out, tasks)
                    if not worker.process.is_alive():
                        worker.process.join()
                        if worker.task is not None:
                            raise TaskError(f"a worker process {death_cause(worker.process.exitcode)} during task "
                                            f"{worker.task}", worker.task, exitcode=worker.process.exitcode)
                        worker.connection.close()
                        running.remove(worker)
        return [results[i] for i in range(len(tasks))]
    finally:
        _stop(running)


def _receive(worker: _Worker, results: dict, bar: tqdm, hand_out: Callable[[_Worker], None], tasks: list) -> None:
    """Everything ``worker`` has sent so far: progress, results (each followed by its next task), errors."""
    while True:
        try:
            if not worker.connection.poll():
                return
            message = worker.connection.recv()
        except (EOFError, OSError):  # it died: the caller sees it in its exit code
            return
        if message[0] == "progress":
            bar.update(message[1])
        elif message[0] == "done":
            results[message[1]] = message[2]
            worker.done += 1
            hand_out(worker)
        else:
            _, index, error, text = message
            worker.task = None
            raise TaskError(f"task {index} failed: {type(error).__name__}: {error}", index, error=error,
                            traceback_text=text)


def _stop(running: list[_Worker]) -> None:
    """Stop the workers still running (SIGTERM, then SIGKILL after a grace period) and reap them."""
    for worker in running:
        if worker.process.is_alive():
            worker.process.terminate()
    for worker in running:
        worker.process.join(_STOP_GRACE_S)
        if worker.process.is_alive():
            worker.process.kill()
            worker.process.join()
        worker.connection.close()
