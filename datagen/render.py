"""Render training frames with Blender into HDF5 shards: ``python -m datagen.render --n 50000``.

``--board`` renders one board (the paper's by default); ``--family DICT_4X4`` renders a random
board of that marker family in every frame (`datagen.family`), with marker labels and lens
distortion (``--distortion-probability``) next to the corner labels.

Frame ``i`` is a pure function of (seed, i, board or family, size, samples, --clean, distortion
probability) and lands in shard
``i // shard_size``. Shards are the unit of work: local worker processes take them from a
pool (and are replaced every ``--recycle`` frames, as Blender's memory grows), and a cluster
splits them with ``--shard-index j --num-shards n`` (job j renders shards s with s % n == j)
with no coordination. A shard file appears only when complete, so a run killed at any moment
and started again with ``--resume`` renders exactly the missing shards.
"""

from __future__ import annotations

import argparse
import os
import socket
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

from datagen.family import FamilySampling, check_prefixes, parse_families
from datagen.render_cluster import add_options as add_cluster_options, submit_render
from datagen.scene import RANDOM_BOARD_SCENE, SceneConfig, random_board_config
from datagen.shards import (INDEX_NAME, ShardReader, index_temporary_writer, list_shards, temporary_prefix,
                            update_index, write_shard)
from datagen.workers import TaskError, death_cause, report_progress, run_tasks
import deepcharuco
from deepcharuco.boards.board import BoardSpec
from deepcharuco.cli.common import output_folder, run_command
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.core.extras import require_extra
from deepcharuco.core.opencv_api import log_errors_only
from deepcharuco.core.platform import describe_os_error

# Arguments that decide the pixels and labels; a resumed run must agree on all of them.
CONTENT_ARGS = ("n", "seed", "board", "width", "height", "samples", "shard_size", "clean", "family",
                "distortion_probability", "shadow_probability")
STALE_INDEX_S = 600  # an index temporary older than this belongs to no live task (each is renamed within ms)
FAMILY_DISTORTION_P = 0.5  # --distortion-probability's default with --family (0 with one board, as before)


@dataclass(frozen=True)
class RenderJob:
    """What one run renders (everything a worker needs, picklable).

    ``board``: the board of every frame, or None with ``families`` (a random board per frame).
    ``distortion_p``: the probability of a distorted frame. ``shadow_p``: the probability of an object between a
    lamp and the board (a cast shadow), None for the scene's own (`SceneConfig.shadow_p`)."""

    n: int
    out: str
    seed: int
    board: BoardSpec | None
    width: int
    height: int
    samples: int | None
    shard_size: int
    clean: bool
    device: str
    threads: int
    families: tuple[str, ...] = ()
    distortion_p: float = 0.0
    shadow_p: float | None = None

    def __post_init__(self) -> None:
        if (self.board is None) == (not self.families):
            raise ValueError("a RenderJob renders one board or random boards of families: give exactly one")

    def content(self) -> dict:
        content = {"n": self.n, "seed": self.seed, "board": self.board.to_dict() if self.board else None,
                   "width": self.width, "height": self.height, "samples": self.samples, "shard_size": self.shard_size,
                   "clean": self.clean}
        # Only where set, so that runs made before these options existed still resume.
        if self.families:
            content["family"] = list(self.families)
        if self.distortion_p:
            content["distortion_probability"] = self.distortion_p
        if self.shadow_p is not None:
            content["shadow_probability"] = self.shadow_p
        return content

    def family_attribute(self) -> dict | None:
        """The shards' ``family`` attribute: how each frame's board was drawn (None for one board)."""
        if not self.families:
            return None
        scene = {key: list(value) if isinstance(value, tuple) else value for key, value in RANDOM_BOARD_SCENE.items()}
        return {"families": list(self.families), "sampling": FamilySampling().to_dict(), "scene": scene}

    def generator(self) -> dict:
        return {"package": "deepcharuco", "version": deepcharuco.__version__, "command": "datagen.render",
                "args": self.content(), "device": self.device}

    @property
    def num_shards(self) -> int:
        return -(-self.n // self.shard_size)

    def frames_of(self, shard: int) -> range:
        return range(shard * self.shard_size, min(self.n, (shard + 1) * self.shard_size))


def scene_config(job: RenderJob) -> SceneConfig:
    config = SceneConfig.clean() if job.clean else SceneConfig()
    config = replace(config, width=job.width, height=job.height)
    if job.families:
        config = random_board_config(config)
    if job.shadow_p is not None:
        config = replace(config, shadow_p=job.shadow_p)
    return replace(config, samples=job.samples) if job.samples else config


def render_shard(job: RenderJob, shard: int) -> int:
    """Render and write one shard; returns its frame count."""
    from datagen.frames import make_frame

    config = scene_config(job)
    # OpenCV warns on stderr about every board whose markers fill more than ~0.8 of their squares (the
    # family's ratios reach 0.85 on purpose, as printed boards do): it would bury the progress bar.
    log_errors_only()  # this is a worker process of its own
    frames = []
    for index in job.frames_of(shard):
        frames.append(make_frame(index, job.seed, job.board, config, threads=job.threads, device=job.device,
                                 families=job.families, distortion_p=job.distortion_p))
        report_progress(1)
    write_shard(job.out, shard, frames, job.board, job.generator(), family=job.family_attribute())
    return len(frames)


def check_existing(job: RenderJob, mine: list[int], resume: bool) -> set[int]:
    """Shards already complete in job.out. Refuses to mix runs with other arguments, and to
    re-run this job over its own finished shards without --resume (shards of the other jobs
    of a cluster split are expected and fine)."""
    out = Path(job.out)
    existing = list_shards(out) if out.exists() else []
    if not existing:
        return set()
    previous = ShardReader(existing[0]).generator.get("args", {})
    content = job.content()
    # An option set there and left out now differs too (optional options are recorded only where set).
    keys = list(content) + [key for key in CONTENT_ARGS if key in previous and key not in content]
    differences = [f"{key}: {previous.get(key)!r} there, {content.get(key)!r} now" for key in keys
                   if previous.get(key) != content.get(key)]
    if differences:
        raise DeepCharucoError(
            f"{out} holds shards rendered with other arguments ({'; '.join(differences)}). "
            f"Rerun with the original arguments, or choose another --out; nothing was touched."
        )
    done = {int(p.stem.split("-")[1]) for p in existing}
    if not resume and done & set(mine):
        raise DeepCharucoError(
            f"{out} already holds {len(done & set(mine))} complete shard(s) of this run. Pass --resume to "
            f"finish it (same arguments), or choose another --out; nothing was touched."
        )
    return done


def remove_stale_temporaries(out: Path, shards: list[int]) -> None:
    """Leftovers of a killed run for the shards this job owns (never complete, never read), and a half-written
    index of a run killed while it rebuilt the index (this run rebuilds it). A fresh index temporary is left alone
    unless its writer was a process of this host that no longer runs (a worker killed mid-write): it may be another
    array task's, renamed a moment later (removing it made that task fail)."""
    for shard in shards:
        for path in out.glob(f"{temporary_prefix(shard)}*"):
            path.unlink(missing_ok=True)
    for path in out.glob(f".{INDEX_NAME}.tmp-*"):
        try:
            if _writer_gone(path.name) or time.time() - path.stat().st_mtime > STALE_INDEX_S:
                path.unlink(missing_ok=True)
        except FileNotFoundError:  # renamed by its task meanwhile
            pass


def _writer_gone(name: str) -> bool:
    """Whether the index temporary ``name`` was written by a process of this host that has ended."""
    writer = index_temporary_writer(name)
    if writer is None or writer[0] != socket.gethostname():
        return False
    try:
        os.kill(writer[1], 0)
    except ProcessLookupError:
        return True
    except PermissionError:  # another user's live process
        return False
    return False


def run_shard_tasks(function, tasks: list[tuple], shards: list[int], out: Path, *, noun: str = "shard",
                    **options) -> None:
    """`run_tasks` for tasks that each write shard ``shards[i]`` into ``out``. Any way the run
    ends early (a task that raises, a worker killed, a full disk) becomes one `DeepCharucoError`
    saying why and how many complete shards were kept, Ctrl-C a `KeyboardInterrupt` saying the
    same; the unfinished shards' temporary files are removed (a killed worker cannot remove its own)."""
    try:
        run_tasks(function, tasks, **options)
        return
    except KeyboardInterrupt:  # a stop, not a failure: exit code 130 through run_command
        remove_stale_temporaries(out, shards)
        raise KeyboardInterrupt(f"{len(list_shards(out))} complete {noun}(s) kept in {out}; rerun the same command "
                                f"with --resume to finish") from None
    except TaskError as failure:
        shard = shards[failure.task_index]
        if failure.error is None:
            reason = f"the worker rendering {noun} {shard} {death_cause(failure.exitcode)}"
        elif isinstance(failure.error, DeepCharucoError):
            reason = str(failure.error)
        elif isinstance(failure.error, OSError):
            reason = f"writing {noun} {shard} failed: {describe_os_error(failure.error)}"
        else:  # a bug: show where
            print(failure.traceback, file=sys.stderr, end="")
            reason = f"rendering {noun} {shard} failed: {type(failure.error).__name__}: {failure.error}"
    finally:
        remove_stale_temporaries(out, shards)
    raise DeepCharucoError(f"{reason}; {len(list_shards(out))} complete {noun}(s) kept in {out}; "
                           f"rerun the same command with --resume to finish")


def run(job: RenderJob, *, workers: int, shard_index: int, num_shards: int, resume: bool, recycle: int,
        quiet: bool = False) -> dict:
    """Render this job's missing shards with ``workers`` processes; returns index.json's content."""
    mine = [s for s in range(job.num_shards) if s % num_shards == shard_index]
    out = output_folder(job.out)  # a writable folder, before anything is rendered
    done = check_existing(job, mine, resume)
    todo = [s for s in mine if s not in done]
    remove_stale_temporaries(out, todo)
    total = sum(len(job.frames_of(s)) for s in todo)
    skipped = sum(len(job.frames_of(s)) for s in mine if s in done)
    if not quiet:
        print(f"datagen.render: {len(todo)} shard(s), {total} frame(s) to render into {out}"
              + (f" ({skipped} frame(s) already there)" if skipped else ""), file=sys.stderr)
    if todo:
        run_shard_tasks(render_shard, [(job, s) for s in todo], todo, out, total=total, unit="frame",
                        workers=workers, tasks_per_child=max(1, recycle // job.shard_size), quiet=quiet)
    return update_index(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m datagen.render", formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description="Render ChArUco training frames with Blender (Cycles) into HDF5 shards with sub-pixel labels.")
    parser.add_argument("--n", type=int, default=1000, help="number of frames in the whole run")
    parser.add_argument("--out", default="data/renders", help="output folder of shard-*.h5 + index.json")
    parser.add_argument("--seed", type=int, default=0, help="run seed: frame i depends only on (seed, i, arguments)")
    parser.add_argument("--board", default=None, help="BoardSpec .json/.yaml file (default: the paper's 5x5 DICT_5X5_50 board)")
    parser.add_argument("--family", default=None,
                        help="instead of --board: a random board of this marker family in every frame (DICT_4X4, "
                             "DICT_5X5, DICT_6X6, DICT_7X7, APRILTAG_36h11; several separated by commas): 3..25 "
                             "squares a side, marker/square 0.5-0.85, legacy or not, first marker ID within 0-249, "
                             "some prints inverted, mirrored or bent")
    parser.add_argument("--distortion-probability", type=float, default=None,
                        help=f"probability that a frame is taken through a distorting lens (k1 uniform in -0.4..+0.1, "
                             f"k2 = k1^2; default: {FAMILY_DISTORTION_P} with --family, 0 with a board, as before)")
    parser.add_argument("--shadow-probability", type=float, default=None,
                        help=f"probability that an object between a lamp and the board casts its shadow on it (in "
                             f"frames with a lamp; default: {SceneConfig.shadow_p}, 0 with --clean)")
    parser.add_argument("--width", type=int, default=320, help="image width in pixels")
    parser.add_argument("--height", type=int, default=240, help="image height in pixels")
    parser.add_argument("--samples", type=int, default=None, help="Cycles samples per pixel (default: 4, --clean 64)")
    parser.add_argument("--shard-size", type=int, default=100, help="frames per shard file")
    parser.add_argument("--clean", action="store_true",
                        help="well-lit, unblurred, noiseless frames of the board alone (label checks, benchmarks)")
    parser.add_argument("--workers", type=int, default=1, help="parallel local render processes")
    parser.add_argument("--threads", type=int, default=0, help="Cycles threads per worker (0: cores / workers)")
    parser.add_argument("--shard-index", type=int, default=0, help="this job's index in a cluster array job")
    parser.add_argument("--num-shards", type=int, default=1, help="number of jobs in the cluster array job")
    parser.add_argument("--device", choices=("cpu", "gpu"), default="cpu", help="Cycles device (gpu: CUDA/OptiX/...)")
    parser.add_argument("--resume", action="store_true", help="continue a run in --out, rendering only missing shards")
    parser.add_argument("--recycle", type=int, default=500, help="replace each worker process after about this many frames")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_cluster_options(parser)
    args = parser.parse_args(argv)

    problems = [f"--{name.replace('_', '-')} must be >= {low}, got {getattr(args, name)}"
                for name, low in (("n", 1), ("width", 16), ("height", 16), ("shard_size", 1), ("workers", 1),
                                  ("num_shards", 1), ("recycle", 1), ("threads", 0), ("seed", 0))
                if getattr(args, name) < low]
    if args.samples is not None and args.samples < 1:
        problems.append(f"--samples must be >= 1, got {args.samples}")
    if args.distortion_probability is not None and not 0.0 <= args.distortion_probability <= 1.0:
        problems.append(f"--distortion-probability must be in [0, 1], got {args.distortion_probability}")
    if args.shadow_probability is not None and not 0.0 <= args.shadow_probability <= 1.0:
        problems.append(f"--shadow-probability must be in [0, 1], got {args.shadow_probability}")
    if not 0 <= args.shard_index < args.num_shards:
        problems.append(f"--shard-index must be in [0, --num-shards), got {args.shard_index} of {args.num_shards}")
    if problems:
        parser.error("; ".join(problems))
    def body() -> int | None:
        # The workers import Blender's module: without it each would fail after the run had started.
        require_extra("python -m datagen.render", ("bpy", "h5py"), "render",
                      " (bpy 5.0.1 installs on Python 3.11 only)")
        if args.family is not None and args.board is not None:
            raise DeepCharucoError("--family and --board exclude each other: --family draws a random board of the "
                                   "family for every frame, --board renders one board; pass only one of them")
        families = parse_families(args.family) if args.family is not None else ()
        for family in families:
            check_prefixes(family)
        board = None if families else (BoardSpec.load(args.board) if args.board else BoardSpec())
        distortion_p = args.distortion_probability
        if distortion_p is None:
            distortion_p = FAMILY_DISTORTION_P if families else 0.0
        threads = args.threads or max(1, (os.cpu_count() or 1) // args.workers)
        job = RenderJob(n=args.n, out=args.out, seed=args.seed, board=board, width=args.width, height=args.height,
                        samples=args.samples or (64 if args.clean else None), shard_size=args.shard_size,
                        clean=args.clean, device=args.device, threads=threads, families=families,
                        distortion_p=float(distortion_p), shadow_p=args.shadow_probability)
        if args.cluster or args.submit:
            check_existing(job, [], resume=True)  # shards of other arguments in --out: refused before submitting
            return submit_render(args)
        started = time.perf_counter()
        index = run(job, workers=args.workers, shard_index=args.shard_index, num_shards=args.num_shards,
                    resume=args.resume, recycle=args.recycle, quiet=args.quiet)
        if not args.quiet:
            print(f"datagen.render: {index['frames']} frame(s) in {len(index['shards'])} shard(s) in {args.out} "
                  f"({time.perf_counter() - started:.0f} s)", file=sys.stderr)

    return run_command(body)


if __name__ == "__main__":
    sys.exit(main())
