"""Running the plan: each stage not done yet, in order, its subprocess given the signals this process gets (a
trainer stopped by Ctrl-C saves its checkpoint), its record written when it finishes, the rates it measured
kept for later plans. ``pipeline`` is a planned `train.pipeline.stages.Pipeline`."""

from __future__ import annotations

import json
import os
import shlex
import signal
import subprocess
import sys
import time
from dataclasses import replace

from datagen.shards import update_index
from train.pipeline.card import write_card
from train.pipeline.checks import checkpoint_step, damaged_files, finished, is_done, marker, missing_output
from train.pipeline.evaluation import bundle_summary, evaluate_model
from train.pipeline.plan import ROOT, PipelineError, human
from train.pipeline.rates import record_rate
from train.pipeline.records import now, remove_tree, write_json
from train.pipeline.stages import Pipeline, Stage


def stop_with_parent() -> None:
    """Run in a stage's child process before it starts (Linux): the child gets SIGTERM when the pipeline dies,
    even by SIGKILL, which no handler can pass on. A stage that outlived its pipeline kept training, and the
    rerun that resumes the run started a second trainer on the same folder."""
    import ctypes

    PR_SET_PDEATHSIG = 1
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def execute(pipeline: Pipeline, stages: list[Stage]) -> int:
    """Run the stages not done yet, in order; 0 when all are done, the stopping signal's 128 + n after a
    Ctrl-C / SIGTERM (the stage in progress saved what it had: rerun to continue)."""
    for number, stage in enumerate(stages, 1):
        if is_done(pipeline.run, stage, pipeline.sizes.frames):
            continue
        code = run_one(pipeline, stage, f"{number}/{len(stages)}")
        if code:
            return code
    print(f"\ndone: {pipeline.run / 'detector.pt'} (Detector(weights=...), detect --weights); card "
          f"{pipeline.run / 'MODEL_CARD.md'}")
    return 0


def run_one(pipeline: Pipeline, stage: Stage, number: str, extra: list[str] = ()) -> int:
    """Run ``stage`` (its command with ``extra`` arguments) and record it finished: 0, or 130/143 when a
    signal stopped it. ``extra`` (a render's shard of an array job) leaves the record to `settle_render`."""
    print(f"\n== stage {number}: {stage.name}: {stage.what} ({stage.size}, ~{human(stage.eta)})", flush=True)
    started = time.perf_counter()
    start_stamp = now()
    if stage.command is None:
        result = run_in_process(pipeline, stage)
    else:
        command = list(stage.command) + list(extra)
        code, result = run_subprocess(pipeline, replace(stage, command=command))
        if code in (130, 143, -signal.SIGINT, -signal.SIGTERM):
            print(f"stopped during stage {stage.name}: rerun the same command to continue", file=sys.stderr)
            return 130 if code in (130, -signal.SIGINT) else 143
        if code != 0:
            raise PipelineError(f"stage {stage.name} failed (exit code {code}; its message is above): fix what "
                                f"it says and rerun the same command, finished stages are kept. The command "
                                f"was: {shlex.join(command)}")
    seconds = time.perf_counter() - started
    if extra:
        return 0
    record(pipeline, stage, seconds, result)
    write_json(marker(pipeline.run, stage), {"stage": stage.name,
                                             "command": shlex.join(stage.command) if stage.command else None,
                                             "seconds": round(seconds, 1), "started": start_stamp,
                                             "finished": now(), "result": result})
    return 0


def run_stage(pipeline: Pipeline, stages: list[Stage], name: str, shard_index: int | None, num_shards: int) -> int:
    """``--stage NAME``: run one stage, as a cluster job does, after checking that the stages before it are
    done. The render stage with a ``shard_index`` renders task ``shard_index``'s shards (as many Cycles threads
    as the job's CPUs), and the task that finds every shard there records the stage finished."""
    names = [stage.name for stage in stages]
    if name not in names:
        raise PipelineError(f"--stage {name!r}: this plan's stages are {', '.join(names)}")
    position = names.index(name)
    stage = stages[position]
    for earlier in stages[:position]:
        if not (settle_render(pipeline, earlier) or is_done(pipeline.run, earlier, pipeline.sizes.frames)):
            raise PipelineError(f"--stage {name}: stage {earlier.name} is not done yet: run it first (python -m "
                                f"train.pipeline ... --cluster slurm --submit runs them in order)")
    if is_done(pipeline.run, stage, pipeline.sizes.frames):
        print(f"stage {name} is done already: nothing to run")
        return 0
    extra: list[str] = []
    if name == "render" and shard_index is not None:
        extra = ["--shard-index", str(shard_index), "--num-shards", str(num_shards)]
        cpus = os.environ.get("SLURM_CPUS_PER_TASK", "")
        if cpus.isdigit():  # the job's CPUs, not the node's (task/none does not bind a job to its cores)
            extra += ["--threads", cpus]
    code = run_one(pipeline, stage, f"{position + 1}/{len(stages)}", extra)
    if code == 0 and extra:
        settle_render(pipeline, stage)
    return code


def settle_render(pipeline: Pipeline, stage: Stage) -> bool:
    """The render stage split over array tasks is finished when all its shards are there and read back: then
    rebuild ``index.json`` (the tasks rewrote it concurrently, each from what it saw) and record the stage.
    True when this recorded it; False for any other stage or while shards are missing."""
    if stage.name != "render" or finished(pipeline.run, stage):
        return False
    renders = pipeline.run / "data" / "renders"
    if missing_output(pipeline.run, stage, pipeline.sizes.frames) or damaged_files(pipeline.run, stage):
        return False
    update_index(renders)
    write_json(marker(pipeline.run, stage), {"stage": stage.name, "command": shlex.join(stage.command),
                                             "seconds": None, "finished": now(),
                                             "result": {"split": "array tasks of a cluster job"}})
    return True


def run_subprocess(pipeline: Pipeline, stage: Stage) -> tuple[int, dict]:
    """Run a stage's command (trainers resumed from their last.pt); SIGINT/SIGTERM sent to this process are
    passed on to it, so it stops as it would on its own (a trainer saves last.pt)."""
    command = list(stage.command)
    if stage.folder is not None:
        if (stage.folder / "last.pt").is_file():
            command.append("--resume")
        else:  # a kill before the first checkpoint: what it logged belongs to no checkpoint
            for leftover in ("log.csv", "best.pt"):
                (stage.folder / leftover).unlink(missing_ok=True)
    for leftover in (pipeline.run / "data").glob(".patches.tmp-*") if stage.name == "patches" else ():
        remove_tree(leftover)  # a patches stage killed before it could clean up (SIGKILL)
    before = progress(pipeline, stage)
    print("$ " + shlex.join(command), flush=True)
    process = subprocess.Popen(command, cwd=ROOT, preexec_fn=stop_with_parent if sys.platform == "linux" else None)
    forwarded = []

    def forward(signum, frame):
        forwarded.append(signum)
        process.send_signal(signum)

    previous = {sig: signal.signal(sig, forward) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        code = process.wait()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if forwarded and code == 0:
        code = 128 + forwarded[0]
    if stage.name == "bundle" and code == 0:
        return code, bundle_summary(pipeline.run / "detector.pt")
    return code, {"progress_before": before, "progress_after": progress(pipeline, stage)}


def progress(pipeline: Pipeline, stage: Stage) -> int:
    """How far a resumable stage got: frames rendered, or a trainer's step."""
    if stage.name == "render":
        index = pipeline.run / "data" / "renders" / "index.json"
        return int(json.loads(index.read_text()).get("frames", 0)) if index.is_file() else 0
    if stage.folder is not None:
        return checkpoint_step(stage.folder / "last.pt")
    return 0


def record(pipeline: Pipeline, stage: Stage, seconds: float, result: dict) -> None:
    """Rates measured by a finished stage, for the ETA of later plans."""
    work = result.get("progress_after", 0) - result.get("progress_before", 0)
    if stage.name == "render" and work > 0:
        record_rate(pipeline.run, "render_s_per_frame", max(0.0, seconds - pipeline.rates["blender_start_s"]) / work,
                    f"render stage {now()}")
    elif stage.name.startswith("charuconet") and work > 0:
        record_rate(pipeline.run, "charuconet_s_per_step", seconds / work, f"{stage.name} stage {now()}")
    elif stage.name == "refinenet" and work > 0:
        record_rate(pipeline.run, "refinenet_s_per_step", seconds / work, f"refinenet stage {now()}")
    elif stage.name.startswith("eval-data"):
        frames = pipeline.sizes.eval_sequences * pipeline.sizes.eval_frames
        record_rate(pipeline.run, "eval_render_s_per_frame", max(0.0, seconds - pipeline.rates["blender_start_s"]) / frames,
                    f"{stage.name} stage {now()}")


def run_in_process(pipeline: Pipeline, stage: Stage) -> dict:
    if stage.name == "evaluate":
        results = evaluate_model(pipeline.run / "detector.pt", pipeline.eval_boards, pipeline.run / "eval", pipeline.sizes,
                                 pipeline.args.quiet)
        write_json(pipeline.run / "eval" / "results.json", results)
        return {"results": str(pipeline.run / "eval" / "results.json")}
    if stage.name == "card":
        write_card(pipeline)
        return {"card": str(pipeline.run / "MODEL_CARD.md")}
    raise AssertionError(stage.name)
