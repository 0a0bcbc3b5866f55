"""train.pipeline --cluster slurm against a real SLURM, not a mock: a one-node cluster on this machine
(scripts/local_slurm.sh installs slurm-wlm and munge with apt-get when missing, and starts munged, slurmctld and
slurmd), a tiny pipeline submitted with one render task cancelled mid-render; bad input refused in one line."""

import datetime as dt
import json
import os
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import REQUIRE_ALL, ROOT, needs_bpy, process_group
from datagen.shards import ShardReader, list_shards
from deepcharuco import BoardSpec
from train.cluster.jobs import Job
from train.cluster.slurm import Resources, choose_partition, parse_minutes
from train.cluster.watch import Tracker, follow
from train.pipeline import checks, command, plan, stages
from train.pipeline.cluster import parse_memory

SCRIPT = ROOT / "scripts" / "local_slurm.sh"
BOARD = BoardSpec(squares_x=4, squares_y=4, square_length=0.04, marker_length=0.03, dictionary="DICT_4X4_50")
# Rates as if recorded by an earlier run: the plan then measures nothing (no Blender probe on the login node).
RATES = {"render_s_per_frame": 1.0, "charuconet_s_per_step": 0.5, "refinenet_s_per_step": 0.2,
         "patch_s_per_patch": 0.002}
TINY = ["--frames", "4", "--charuconet-steps", "4", "--refinenet-steps", "2", "--synthetic-patches", "200",
        "--eval-sequences", "1", "--eval-frames", "31", "--eval-images", "1", "--image-size", "160x120",
        "--samples", "2", "--batch-size", "2", "--workers", "0", "--device", "cpu", "--quiet"]
# Two render tasks of one CPU each run side by side on a 2-core node; the watcher looks every second.
ON_SLURM = ["--cluster", "slurm", "--num-shards", "2", "--cpus-per-task", "1", "--poll", "1"]
EPOCH = {"SOURCE_DATE_EPOCH": "1700000000"}  # the shards' one time stamp, for byte-identical renders
HANG_S = 1800  # a hang guard, not a bound on speed


def cluster_is_up() -> bool:
    if shutil.which("sinfo") is None or shutil.which("scontrol") is None:
        return False
    ping = subprocess.run(["scontrol", "ping"], capture_output=True, text=True)
    nodes = subprocess.run(["sinfo", "-h", "-o", "%T"], capture_output=True, text=True)
    return "is UP" in ping.stdout and any(s in nodes.stdout for s in ("idle", "mixed", "allocated"))


@pytest.fixture(scope="module")
def local_slurm() -> None:
    """A running SLURM cluster: the one here, or one started by scripts/local_slurm.sh (root, apt). Where it cannot
    be had the tests skip saying why; under DEEPCHARUCO_REQUIRE_ALL=1 (CI) they fail instead."""
    if cluster_is_up():
        return
    result = subprocess.run(["bash", str(SCRIPT)], capture_output=True, text=True, timeout=900)
    if result.returncode != 0 or not cluster_is_up():
        reason = ("no SLURM cluster here, and scripts/local_slurm.sh could not start one: "
                  + (result.stderr.strip().splitlines() or ["no message"])[-1])
        if REQUIRE_ALL:
            pytest.fail(reason + " (DEEPCHARUCO_REQUIRE_ALL=1: the cluster tests must run)")
        pytest.skip(reason)


def new_run(tmp_path: Path) -> tuple[Path, Path]:
    board = BOARD.save(tmp_path / "board.yaml")
    run = tmp_path / "run"
    run.mkdir()
    (run / "rates.json").write_text(json.dumps({k: {"value": v, "source": "test"} for k, v in RATES.items()}))
    return board, run


def wait_for(condition, process: subprocess.Popen, output: Path) -> None:
    waited = 0.0
    while not condition():
        if process.poll() is not None:
            raise AssertionError(f"the watcher ended (code {process.returncode}) too soon:\n{output.read_text()[-3000:]}")
        assert waited < HANG_S, f"still waiting after {HANG_S} s: {output.read_text()[-3000:]}"
        time.sleep(0.1)
        waited += 0.1


def planned(board: Path, run: Path) -> stages.Pipeline:
    args = command.build_parser().parse_args(["--board", str(board), "--out", str(run), *TINY])
    pipeline = stages.Pipeline(args, plan.check_target(args))
    pipeline.plan()
    return pipeline


@needs_bpy
def test_pipeline_on_slurm_resubmits_a_cancelled_render_task(local_slurm, tmp_path):
    """A tiny pipeline submitted to SLURM (2 render array tasks, 4 + 2 training steps, bundle, evaluation, card);
    render task 1 is cancelled with scancel mid-render: the watcher resubmits it (and the jobs that waited on it),
    the run completes with the same shard bytes as a direct render, every stage started after the one before it
    finished, and a second submission of the finished run submits nothing."""
    board, run = new_run(tmp_path)
    argv = [sys.executable, "-m", "train.pipeline", "--board", str(board), "--out", str(run), *TINY, *ON_SLURM,
            "--submit"]
    env = {**os.environ, **EPOCH, "PYTHONPATH": str(ROOT)}
    output = tmp_path / "watcher.txt"
    renders = run / "data" / "renders"
    with open(output, "w") as sink, process_group(argv, cwd=ROOT, stdout=sink, stderr=subprocess.STDOUT,
                                                   env=env) as watcher:
        jobs = run / "cluster" / "jobs.json"
        wait_for(jobs.is_file, watcher, output)
        render_id = json.loads(jobs.read_text())["submissions"][0]["id"]
        log = run / "cluster" / "logs" / f"render-{render_id}_1.log"
        wait_for(lambda: log.is_file() and "-m datagen.render" in log.read_text(), watcher, output)
        assert not (renders / "shard-00003.h5").exists()  # task 1 renders shards 1 and 3: it is mid-render
        assert "--shard-index 1 --num-shards 2" in log.read_text()  # its own share of the shards
        subprocess.run(["scancel", f"{render_id}_1"], check=True)
        assert watcher.wait(timeout=HANG_S) == 0, output.read_text()[-3000:]
    text = output.read_text()
    assert f"render task 1: job {render_id}_1 ended CANCELLED" in text and "resubmitted (retry 1 of 2)" in text, text
    assert "patches: cancelled" in text  # it waited on the cancelled task: submitted again after the new one

    # Every stage's outputs verify, the shards of both tasks among them, and they hold a direct render's bytes.
    pipeline = planned(board, run)
    assert all(checks.is_done(run, stage, pipeline.sizes.frames) for stage in pipeline.stages())
    shards = list_shards(renders)
    assert [p.name for p in shards] == [f"shard-{i:05d}.h5" for i in range(4)]
    assert all(len(ShardReader(p)) == 1 for p in shards)
    direct = shlex.split(json.loads((run / "stages" / "render.json").read_text())["command"])
    direct = [a for a in direct if a not in ("--resume", "--quiet")]
    direct[direct.index("--out") + 1] = str(tmp_path / "direct")
    subprocess.run(direct, cwd=ROOT, env=env, check=True, capture_output=True)
    for shard in shards:
        assert shard.read_bytes() == (tmp_path / "direct" / shard.name).read_bytes(), shard.name

    # The stages ran in order: each started after the one before it finished (the job records' times).
    records = [json.loads(checks.marker(run, stage).read_text()) for stage in pipeline.stages()]
    for before, after in zip(records, records[1:]):
        assert dt.datetime.fromisoformat(after["started"]) >= dt.datetime.fromisoformat(before["finished"]), \
            (before["stage"], after["stage"])

    # A second submission of the finished run submits nothing; --status says every stage is done.
    submitted = jobs.read_bytes()
    again = subprocess.run(argv, cwd=ROOT, env=env, capture_output=True, text=True, timeout=HANG_S)
    assert again.returncode == 0 and "submitted job" not in again.stdout, again.stdout + again.stderr
    assert jobs.read_bytes() == submitted
    status = subprocess.run([*argv[:-1], "--status"], cwd=ROOT, env=env, capture_output=True, text=True)
    assert status.returncode == 0 and status.stdout.count(": done") == len(records), status.stdout


def test_what_the_cluster_cannot_give_is_refused_in_one_line(local_slurm, tmp_path, capsys):
    """An unknown partition, more CPUs, memory or GPUs than any node has: exit 2, one line naming the problem and
    the fix, and no plan, no scripts, nothing submitted."""
    board, run = new_run(tmp_path)
    nodes = subprocess.run(["sinfo", "-h", "-o", "%P %c"], capture_output=True, text=True).stdout.split()
    cpus = int(nodes[1].rstrip("+"))
    cases = [(["--partition", "no-such-partition"], "the cluster has no such partition (sinfo lists: "),
             (["--cpus-per-task", str(cpus + 1)], f"{cpus + 1} CPUs (--cpus-per-task), its nodes have at most {cpus}"),
             (["--mem", "100000G"], "MB of memory (--mem), its nodes have at most"),
             (["--gpus", "64"], "64 GPU(s) (--gpus), its nodes have"),
             (["--cpus-per-task", "0"], "--cpus-per-task 0: give 1 or more")]
    for extra, message in cases:
        code = command.main(["--board", str(board), "--out", str(run), *TINY, *ON_SLURM, "--submit", *extra])
        err = capsys.readouterr().err
        assert code == 2 and message in err and err.count("\n") == 1 and err.startswith("error: "), (extra, err)
    assert not (run / "plan.json").exists() and not (run / "cluster").exists()


def test_submit_without_sbatch_is_refused(tmp_path, capsys, monkeypatch):
    """No SLURM on the PATH: --submit (train.pipeline and datagen.render) says so in one line, exit 2."""
    board, run = new_run(tmp_path)
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    code = command.main(["--board", str(board), "--out", str(run), *TINY, *ON_SLURM, "--submit"])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("error: --submit needs SLURM's sbatch and squeue on the PATH") \
        and err.count("\n") == 1, err
    code = command.main(["--board", str(board), "--out", str(run), *TINY, "--submit"])
    assert code == 2 and "--submit, --no-wait and --status go with --cluster slurm" in capsys.readouterr().err
    assert sorted(p.name for p in run.iterdir()) == ["rates.json"]
    from datagen import render

    code = render.main(["--n", "4", "--out", str(tmp_path / "renders"), "--num-shards", "2", "--cluster", "slurm",
                        "--submit"])
    err = capsys.readouterr().err
    assert code == 2 and "--submit needs SLURM's sbatch" in err and err.count("\n") == 1, err


@pytest.mark.parametrize("text, minutes", [("90", 90), ("1:30", 2), ("4:00:00", 240), ("1-02", 1560),
                                           ("2-00:30:00", 2910), ("infinite", None), ("UNLIMITED", None)])
def test_slurm_times_read_as_sbatch_reads_them(text, minutes):
    assert parse_minutes(text) == minutes


@pytest.mark.parametrize("text, mb", [("16G", 16384), ("8000M", 8000), ("8000", 8000), ("1T", 1048576), ("512K", 1)])
def test_memory_reads_as_sbatch_reads_it(text, mb):
    assert parse_memory(text) == mb


@needs_bpy
def test_a_bare_render_as_an_array_job(local_slurm, tmp_path):
    """datagen.render --num-shards 2 --cluster slurm --submit: two array tasks render the shards a direct render
    makes, byte for byte, and the index counts them all."""
    args = ["--n", "2", "--shard-size", "1", "--width", "64", "--height", "48", "--samples", "1"]
    env = {**os.environ, **EPOCH, "PYTHONPATH": str(ROOT)}
    render = [sys.executable, "-m", "datagen.render", *args]
    cluster = subprocess.run([*render, "--out", str(tmp_path / "array"), "--num-shards", "2", "--cluster", "slurm",
                              "--submit", "--cpus-per-task", "1", "--poll", "1"], cwd=ROOT, env=env,
                             capture_output=True, text=True, timeout=HANG_S)
    assert cluster.returncode == 0, cluster.stdout + cluster.stderr
    assert "render: submitted job" in cluster.stdout and "(tasks 0,1 of 2)" in cluster.stdout
    subprocess.run([*render, "--out", str(tmp_path / "direct"), "--quiet"], cwd=ROOT, env=env, check=True)
    shards = list_shards(tmp_path / "array")
    assert [p.name for p in shards] == ["shard-00000.h5", "shard-00001.h5"]
    for shard in shards:
        assert shard.read_bytes() == (tmp_path / "direct" / shard.name).read_bytes(), shard.name
    assert json.loads((tmp_path / "array" / "index.json").read_text())["frames"] == 2


def test_a_job_that_can_never_start_stops_the_watcher(local_slurm, tmp_path, capsys):
    """A job sbatch accepts but no node can run (more CPUs than the partition's nodes: squeue's PartitionConfig)
    is cancelled and reported, instead of being waited on for ever."""
    partition = choose_partition(None)
    job = Job("too-big", ["true"], Resources(cpus=partition.cpus + 1, mem_mb=0, gpus=0, minutes=15), lambda: False)
    tracker = Tracker([job], tmp_path / "cluster", tmp_path, "never", partition, max_retries=0)
    assert follow(tracker, wait=True, poll=0.5) == 1
    err = capsys.readouterr().err
    assert "too-big: job" in err and "can never start (SLURM says PartitionConfig)" in err, err
    job_id = tracker.submissions()[0]["id"]
    assert job_id not in subprocess.run(["squeue", "-h", "-o", "%i"], capture_output=True, text=True).stdout.split()
