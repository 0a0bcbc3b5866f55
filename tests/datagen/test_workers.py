"""Render workers that die or fail, and a full disk: the run ends at once with a clear error, complete
shards stay, temporaries go (no Blender here: the tasks are small functions; tests/datagen/test_render.py kills
a real render worker)."""

import errno
import os
import resource
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import ROOT

from datagen.render import run_shard_tasks
from datagen.shards import list_shards, shard_name, temporary_prefix, write_patch_shard
from datagen.workers import TaskError, report_progress, run_tasks
from deepcharuco.core.errors import DeepCharucoError

HANG_S = 60  # far longer than any of these runs: reaching it means the parent hung


@pytest.fixture(autouse=True)
def no_hang():
    """Fail (rather than wait forever) when run_tasks hangs, as multiprocessing.Pool did on a dead worker."""
    def hung(signum, frame):
        raise AssertionError(f"run_tasks still waiting after {HANG_S} s")

    previous = signal.signal(signal.SIGALRM, hung)
    signal.alarm(HANG_S)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, previous)


def write_or_die(out: str, shard: int, action: str) -> int:
    """A stand-in for a render task: writes shard ``shard`` unless ``action`` says to die or fail first
    (after leaving a temporary file behind, as a worker killed mid-write does)."""
    report_progress(1)
    if action != "ok":
        Path(out, f"{temporary_prefix(shard)}host-{os.getpid()}").write_bytes(b"half a shard")
    if action == "kill":
        os.kill(os.getpid(), signal.SIGKILL)
    if action == "full":
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(Path(out, shard_name(shard))))
    if action == "bug":
        raise ZeroDivisionError("a bug")
    patches = np.zeros((1, 24, 24), np.uint8)
    write_patch_shard(out, shard, patches, np.full((1, 2), 8.0, np.float32), {"source": np.array(["test"])}, {})
    return shard


def test_results_in_task_order_across_recycled_workers(tmp_path):
    tasks = [(str(tmp_path), s, "ok") for s in range(5)]
    assert run_tasks(write_or_die, tasks, total=5, unit="shard", workers=2, tasks_per_child=2, quiet=True) == list(range(5))
    assert len(list_shards(tmp_path)) == 5


@pytest.mark.parametrize("action, messages", [
    ("kill", ["the worker rendering shard 1 killed by SIGKILL (the out-of-memory killer"]),
    ("full", ["writing shard 1 failed: cannot access", "shard-00001.h5: No space left on device (free some space"]),
    ("bug", ["rendering shard 1 failed: ZeroDivisionError: a bug"]),
])
def test_a_dead_or_failing_worker_ends_the_run_with_a_clear_error(tmp_path, action, messages):
    tasks = [(str(tmp_path), 0, "ok"), (str(tmp_path), 1, action)]
    with pytest.raises(DeepCharucoError) as caught:  # a hang is caught by `no_hang`'s alarm
        run_shard_tasks(write_or_die, tasks, [0, 1], tmp_path, total=2, unit="frame", workers=1, quiet=True)
    text = str(caught.value)
    assert all(m in text for m in messages), text
    assert "1 complete shard(s) kept" in text and "--resume" in text
    assert [p.name for p in list_shards(tmp_path)] == ["shard-00000.h5"]
    assert not [p for p in tmp_path.iterdir() if ".tmp-" in p.name], "temporaries left behind"


def test_task_error_keeps_the_exit_code_and_the_remote_traceback(tmp_path):
    with pytest.raises(TaskError) as killed:
        run_tasks(write_or_die, [(str(tmp_path), 0, "kill")], total=1, unit="shard", quiet=True)
    assert killed.value.exitcode == -signal.SIGKILL and killed.value.task_index == 0 and killed.value.error is None
    with pytest.raises(TaskError) as failed:
        run_tasks(write_or_die, [(str(tmp_path), 0, "bug")], total=1, unit="shard", quiet=True)
    assert isinstance(failed.value.error, ZeroDivisionError) and "write_or_die" in failed.value.traceback


def test_a_full_disk_while_writing_a_shard_is_an_error_not_a_crash(tmp_path):
    """HDF5 crashes the process (SIGSEGV) when a write fails; shards are built in memory and written by
    Python, so a full disk (here a file-size limit, which fails writes with EFBIG) is an OSError and
    the temporary file is removed."""
    script = ("import numpy as np, sys\n"
              "from datagen.shards import write_patch_shard\n"
              "patches = np.random.default_rng(0).integers(0, 256, (2000, 24, 24), dtype=np.uint8)\n"
              "try:\n"
              "    write_patch_shard(sys.argv[1], 0, patches, np.full((2000, 2), 8.0, np.float32), "
              "{'source': np.array(['x'] * 2000)}, {})\n"
              "except OSError as error:\n"
              "    print('OSError', error.errno)\n")
    limit = 100_000  # bytes: the shard is ~1.2 MB of incompressible patches
    done = subprocess.run([sys.executable, "-c", script, str(tmp_path)], cwd=ROOT, capture_output=True, text=True,
                          preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit)), timeout=HANG_S)
    assert done.returncode == 0, f"crashed with {done.returncode}: {done.stderr[-2000:]}"
    assert done.stdout.strip() == f"OSError {errno.EFBIG}"
    assert list(tmp_path.iterdir()) == []
