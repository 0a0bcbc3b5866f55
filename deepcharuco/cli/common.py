"""What every command line of the project shares: one-line errors and output paths checked up front.

Bad input, a read-only or mistyped ``--out`` and a full disk are the user's to fix, not bugs: a
command says what went wrong and what to do in one line on stderr and exits with code 2, instead
of a traceback. Bugs (any other exception) still show their traceback.
"""

from __future__ import annotations

import os
import signal
import sys
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Callable

from deepcharuco.boards.board import BoardSpec
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.core.platform import available_cpus, describe_os_error
from deepcharuco.geometry.camera import Camera

EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as a shell reports a command stopped by Ctrl-C
EXIT_TERMINATED = 143  # 128 + SIGTERM (kill, a job scheduler's stop)


def run_command(body: Callable[[], int | None]) -> int:
    """``body()``'s exit code (None: 0); a `DeepCharucoError` or `OSError` becomes ``error: ...`` on
    stderr and exit code 2; Ctrl-C (`KeyboardInterrupt`) becomes ``stopped: ...`` and exit code 130,
    without a traceback (``KeyboardInterrupt("what was kept and how to go on")`` says more). SIGTERM is
    taken as Ctrl-C is (the body's cleanup runs: output locks released, nothing half-written), and exits 143."""
    terminated = []

    def on_sigterm(signum, frame):
        terminated.append(signum)
        raise KeyboardInterrupt

    # Only the main thread may set a handler; a body that sets its own (the trainers') takes over meanwhile.
    previous = signal.signal(signal.SIGTERM, on_sigterm) if threading.current_thread() is threading.main_thread() \
        else None
    try:
        code = body()
    except KeyboardInterrupt as stop:
        reason = stop.args[0] if stop.args else "interrupted (Ctrl-C) before the end"
        print(f"stopped{' (SIGTERM)' if terminated else ''}: {reason}", file=sys.stderr)
        return EXIT_TERMINATED if terminated else EXIT_INTERRUPTED
    except DeepCharucoError as error:
        print(f"error: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except OSError as error:
        print(f"error: {describe_os_error(error)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    return 0 if code is None else code


def output_folder(path: str | Path, option: str = "--out") -> Path:
    """Create the output folder ``path`` (and its parents) and check that files can be written in it.

    Raises `DeepCharucoError` naming ``option`` when ``path`` is a file, or the folder cannot be
    created or written to — before any work is done, so nothing half-made is left behind."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise DeepCharucoError(f"{option} {path} is a file, not a folder: give a folder path")
    try:
        path.mkdir(parents=True, exist_ok=True)
        descriptor, probe = tempfile.mkstemp(prefix=".write-test-", dir=path)
        os.close(descriptor)
        os.unlink(probe)
    except OSError as error:
        raise DeepCharucoError(f"{option} {path}: cannot write there ({error.strerror or error}): "
                               f"choose a writable folder or fix its permissions") from None
    return path


@contextmanager
def no_empty_folders_on_failure(path: str | Path) -> Iterator[None]:
    """A run that makes the folder ``path`` (and its missing parents): where it fails (an exception, Ctrl-C among
    them), those of the folders it made that are empty are removed again, deepest first, so a failed run leaves
    none behind. A folder holding anything stays, with its parents; a folder that existed before is never removed."""
    path = Path(path).absolute()
    made = [p for p in [path, *path.parents] if not p.exists()]  # deepest first
    try:
        yield
    except BaseException:
        for folder in made:
            try:
                folder.rmdir()
            except OSError:  # not empty (or already gone): it and its parents stay
                break
        raise


def check_output_folder(path: str | Path, option: str = "--out") -> Path:
    """What `output_folder` checks, without creating anything (for a dry run): ``path`` is a folder or can be
    made in a writable folder. Raises `DeepCharucoError` naming ``option`` otherwise."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise DeepCharucoError(f"{option} {path} is a file, not a folder: give a folder path")
    existing = next(p for p in [path, *path.absolute().parents] if p.exists())
    if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        raise DeepCharucoError(f"{option} {path}: cannot write there ({existing} is not a writable folder): "
                               f"choose a writable folder or fix its permissions")
    return path


def output_file(path: str | Path, option: str = "--out") -> Path:
    """Check that the file ``path`` can be written (its folder is created): not a folder, and its
    folder writable (files here are written to a temporary name and renamed, so the folder's
    permissions are what count). Raises `DeepCharucoError` naming ``option`` otherwise."""
    path = Path(path)
    if path.is_dir():
        raise DeepCharucoError(f"{option} {path} is a folder: give a file path, e.g. {path / 'detector.pt'}")
    output_folder(path.parent, option=f"{option}'s folder")
    return path


# A board file's lengths are metres; a square above this many was almost surely written in millimetres or centimetres.
LARGEST_LIKELY_SQUARE_M = 1.0


def load_board(path: str | Path) -> BoardSpec:
    """The board file ``path`` (`BoardSpec.load`), with a warning line on stderr where its squares are implausibly large
    for metres (over `LARGEST_LIKELY_SQUARE_M`): a length written in millimetres (54 for 0.054) is read as metres, and
    poses and rig translations then come out in millimetres, consistently but not in the metres the docs promise."""
    board = BoardSpec.load(path)
    if board.square_length > LARGEST_LIKELY_SQUARE_M:
        print(f"warning: {path}: square_length {board.square_length:g} m: board files give lengths in metres (54 mm is "
              f"0.054); as written, poses and rig translations come out in the file's own unit", file=sys.stderr)
    return board


def four_term_note(path: str | Path, camera: Camera) -> str | None:
    """A note line where the camera file ``path`` gives 4 distortion coefficients and no fisheye model: read as OpenCV's
    pinhole k1 k2 p1 p2, which is also how a ``cv2.fisheye`` file without its ``distortion_model`` reads (its poses
    then a few tenths of a pixel off, without a word); None otherwise."""
    if camera.model == "fisheye" or camera.dist.size != 4:
        return None
    return (f"note: {path} has 4 distortion coefficients and no fisheye model: read as OpenCV's k1 k2 p1 p2; if it is "
            f"cv2.fisheye's, add 'distortion_model: fisheye' to it")


def jobs_warning(jobs: int, cpus: int | None = None) -> str | None:
    """A warning line where ``jobs`` worker processes are at least the ``cpus`` this process may run on (default: what
    `available_cpus` says), else None. The workers and this process, which reads the frames and writes the results,
    then share the CPUs: on a 2-CPU machine ``--jobs 2`` took 1.4x (detect, a 628-frame video) and 1.8x (calibrate,
    111 frames) the time of one process (docs/usage.md)."""
    cpus = available_cpus() if cpus is None else cpus
    if jobs <= 1 or jobs < cpus:
        return None
    return (f"warning: --jobs {jobs} on {cpus} CPU(s): the workers and this process share them, which is often "
            f"slower than one process (--jobs 1); leave a CPU free for reading the frames")


def pick_device(name: str) -> "torch.device":
    """The torch device ``name`` names ("auto": CUDA, else MPS, else CPU); `DeepCharucoError` when it is
    not a device name or this machine (or this torch build) does not have it."""
    import torch  # here, so that commands without a network do not load torch
    if name != "auto":
        try:
            device = torch.device(name)
        except RuntimeError:
            raise DeepCharucoError(f"--device {name!r} is not a device: use auto, cpu, cuda, cuda:N or mps") from None
        if device.type == "cuda":
            count = torch.cuda.device_count() if torch.cuda.is_available() else 0
            if count == 0:
                raise DeepCharucoError(f"--device {name}: no CUDA GPU is usable here (this torch {torch.__version__} "
                                       f"{'has no CUDA support' if torch.version.cuda is None else 'sees no GPU'}): "
                                       f"use --device cpu or auto")
            if device.index is not None and device.index >= count:
                raise DeepCharucoError(f"--device {name}: only {count} CUDA GPU(s) here (cuda:0..cuda:{count - 1})")
        elif device.type == "mps" and not (getattr(torch.backends, "mps", None) and torch.backends.mps.is_available()):
            raise DeepCharucoError(f"--device {name}: MPS (Apple GPU) is not available here: use --device cpu or auto")
        elif device.type not in ("cpu", "cuda", "mps"):
            raise DeepCharucoError(f"--device {name}: use cpu, cuda or mps")
        return device
    if torch.cuda.is_available():
        return torch.device("cuda", int(os.environ.get("LOCAL_RANK", 0)))
    if getattr(torch.backends, "mps", None) and torch.backends.mps.is_available():
        return torch.device("mps")
    return torch.device("cpu")
