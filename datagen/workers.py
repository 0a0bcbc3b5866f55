"""Render tasks in local worker processes behind one progress bar.

Blender keeps state between renders and grows in memory, prints a line per render on the C
stdout, and is imported once per process: so renders run in ``spawn``-ed worker processes
(replaced every few tasks), with their stdout silenced, reporting progress to the parent
through a queue. A task is a picklable module-level function and its arguments.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue
from typing import Any, Callable

from tqdm import tqdm

_PROGRESS: "mp.Queue | None" = None


def report_progress(units: int = 1) -> None:
    """Advance the parent's progress bar by ``units`` (a no-op outside a `run_tasks` worker)."""
    if _PROGRESS is not None:
        _PROGRESS.put(units)


def _init_worker(progress: "mp.Queue") -> None:
    global _PROGRESS
    _PROGRESS = progress
    # Blender prints a line per render on the C stdout; keep the parent's progress bar readable.
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)


def run_tasks(function: Callable[..., Any], tasks: list[tuple], *, total: int, unit: str, workers: int = 1,
              tasks_per_child: int | None = None, quiet: bool = False) -> list[Any]:
    """``function(*task)`` for every task in ``workers`` processes; returns the results in task order.

    ``total``: progress units that the tasks will report with `report_progress` (the bar's ETA
    is as good as this estimate). A worker's exception is re-raised here as soon as it happens;
    KeyboardInterrupt terminates the workers and is re-raised (whatever they had completed stays).
    """
    if not tasks:
        return []
    context = mp.get_context("spawn")
    progress = context.Queue()
    with context.Pool(workers, initializer=_init_worker, initargs=(progress,), maxtasksperchild=tasks_per_child) as pool, \
            tqdm(total=total, unit=unit, disable=quiet, smoothing=0.1) as bar:
        try:
            results = [pool.apply_async(function, task) for task in tasks]
            while True:
                try:
                    bar.update(progress.get(timeout=0.5))
                except queue.Empty:
                    pass
                for result in results:
                    if result.ready() and not result.successful():
                        result.get()  # re-raises the worker's exception
                if all(r.ready() for r in results):
                    break
            while not progress.empty():
                bar.update(progress.get())
            return [r.get() for r in results]
        except KeyboardInterrupt:
            pool.terminate()
            raise
