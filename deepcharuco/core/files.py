"""Writing a command's output files so that a failure never destroys what was there.

Every file is written under a hidden temporary name in its own folder, flushed to disk and renamed
over the target only when complete (`atomic_file`, `write_atomic`): a full disk, a file-size limit or
a kill leaves the previous file as it was, and the failure is a `DeepCharucoError` naming the file
and the fix (exit code 2 through `deepcharuco.cli.common.run_command`). `refuse_foreign` keeps a command
from overwriting a file it did not write; `OutputLock` keeps two runs from writing one file at once.
"""

from __future__ import annotations

import contextlib
import os
import zlib
from pathlib import Path
from typing import Callable, Iterator

from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.core.platform import explain_os_error

try:  # POSIX; on Windows the lock is msvcrt's
    import fcntl
except ImportError:  # pragma: no cover - not on this project's CI
    fcntl = None
    import msvcrt


class OutputError(DeepCharucoError):
    """An output file that cannot be written, or must not be."""


def temporary_name(path: Path) -> Path:
    """The hidden name ``path`` is written under before it is renamed into place (same folder, same suffix,
    so that writers that choose a format by the suffix, such as OpenCV's, keep choosing it)."""
    return path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")


def _failed(path: Path, error: OSError, what: str = "") -> OutputError:
    kept = "the previous file is unchanged" if path.exists() else "nothing was written"
    return OutputError(f"could not write {what + ' ' if what else ''}{path}: {explain_os_error(error)}; {kept}")


@contextlib.contextmanager
def atomic_file(path: str | Path, mode: str = "w", what: str = "", **open_args) -> Iterator:
    """``open(path, mode)`` that writes a temporary file and renames it onto ``path`` when the block ends
    without an exception; on one (a full disk included) the temporary file is removed, ``path`` is left as
    it was and an `OSError` becomes `OutputError` (naming the file as ``what``, e.g. "the overlay")."""
    path = Path(path)
    temporary = temporary_name(path)
    try:
        with open(temporary, mode, **open_args) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    except OSError as error:
        temporary.unlink(missing_ok=True)
        raise _failed(path, error, what) from None
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def write_atomic(path: str | Path, data: str | bytes, what: str = "") -> Path:
    """Write ``data`` (text as UTF-8) to ``path``, whole or not at all (`write_together` of one file)."""
    return write_together({Path(path): data}, what)[0]


def write_together(files: dict[Path, str | bytes], what: str = "") -> list[Path]:
    """Write several files that belong together (a camera file and its report) as one: every one is written
    to its temporary name first, and only when all are complete are they renamed into place; a failure
    (an `OutputError` naming the file, as ``what`` where given) leaves every target as it was."""
    written: list[tuple[Path, Path]] = []
    path = None
    try:
        for path, data in files.items():
            path = Path(path)
            temporary = temporary_name(path)
            written.append((temporary, path))
            with open(temporary, "wb") as handle:
                handle.write(data.encode("utf-8") if isinstance(data, str) else data)
                handle.flush()
                os.fsync(handle.fileno())
        for temporary, path in written:
            os.replace(temporary, path)
    except OSError as error:
        raise _failed(path, error, what) from None
    finally:
        for temporary, _ in written:
            temporary.unlink(missing_ok=True)
    return [path for _, path in written]


def refuse_foreign(path: str | Path, is_ours: Callable[[Path], bool], what: str, force: bool = False,
                   option: str = "--out") -> None:
    """Refuse (`OutputError`) to overwrite an existing ``path`` that ``is_ours`` does not recognise as a
    ``what`` (a camera file, a report, ...), unless ``force``. Each command's test looks for a mark inside the
    files it writes (a header, a comment, a PNG text chunk), not just their format: a user's own PNG, PDF or board
    file of the same format is kept."""
    path = Path(path)
    if force or not path.is_file():
        return
    try:
        ours = is_ours(path)
    except (OSError, ValueError, UnicodeDecodeError):
        ours = False
    if not ours:
        raise OutputError(f"{option} {path} exists and is not a {what}: choose another {option}, or pass --force "
                          f"to overwrite it")


def starts_with(prefix: bytes) -> Callable[[Path], bool]:
    """An ``is_ours`` test for `refuse_foreign`: the file begins with ``prefix``."""
    def test(path: Path) -> bool:
        with open(path, "rb") as handle:
            return handle.read(len(prefix)) == prefix
    return test


def contains(mark: bytes, within: int = 1 << 16) -> Callable[[Path], bool]:
    """An ``is_ours`` test for `refuse_foreign`: ``mark`` lies in the file's first ``within`` bytes."""
    def test(path: Path) -> bool:
        with open(path, "rb") as handle:
            return mark in handle.read(within)
    return test


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_IHDR_END = len(PNG_SIGNATURE) + 4 + 4 + 13 + 4  # length, type, the 13 header bytes, CRC


def png_marked(data: bytes, software: str) -> bytes:
    """PNG ``data`` with a ``tEXt`` chunk ``Software`` = ``software`` right after the header: the mark by which a
    command later knows a PNG as one it wrote (`png_mark`), and may replace it without ``--force``."""
    if not data.startswith(PNG_SIGNATURE):
        raise ValueError("not a PNG")
    body = b"tEXt" + b"Software\0" + software.encode("latin-1")
    chunk = (len(body) - 4).to_bytes(4, "big") + body + zlib.crc32(body).to_bytes(4, "big")
    return data[:_IHDR_END] + chunk + data[_IHDR_END:]


def png_mark(software: str) -> Callable[[Path], bool]:
    """An ``is_ours`` test for `refuse_foreign`: a PNG that `png_marked` marked with ``software``."""
    marked = contains(b"tEXtSoftware\0" + software.encode("latin-1"), 256)  # the chunk follows the header
    return lambda path: starts_with(PNG_SIGNATURE)(path) and marked(path)



# An MP4 (ISO base media file) is a run of boxes, each (size: 4 bytes big-endian, type: 4 bytes, payload); a top-level
# "free" box is padding every reader skips, so a mark in one changes no frame.
MP4_FREE = b"free"
MAX_MP4_BOXES = 4096


def _mp4_boxes(path: Path) -> Iterator[tuple[bytes, int, int]]:
    """(type, payload offset, payload size) of each top-level box of the MP4 ``path``; ``ValueError`` where its box
    sizes do not add up to the file (not an MP4, or cut short), or a box runs to the end of the file (size 0)."""
    end = path.stat().st_size
    with open(path, "rb") as handle:
        offset = 0
        for _ in range(MAX_MP4_BOXES):
            if offset == end:
                return
            handle.seek(offset)
            header = handle.read(8)
            if len(header) < 8:
                raise ValueError("cut short")
            size, kind = int.from_bytes(header[:4], "big"), header[4:]
            start = offset + 8
            if size == 1:  # a 64-bit size follows the type
                size, start = int.from_bytes(handle.read(8), "big"), offset + 16
            if size < start - offset or offset + size > end:
                raise ValueError("not an MP4 box")
            yield kind, start, offset + size - start
            offset += size
        raise ValueError("too many boxes")


def mp4_marked(path: str | Path, software: str) -> None:
    """Append to the MP4 file ``path`` a top-level ``free`` box holding ``software``: the mark by which a command
    later knows a video as one it wrote (`mp4_mark`). ``ValueError`` where ``path`` is not a well-formed MP4."""
    path = Path(path)
    list(_mp4_boxes(path))  # its boxes add up: the new one lands after the last
    payload = software.encode("latin-1")
    with open(path, "ab") as handle:
        handle.write((8 + len(payload)).to_bytes(4, "big") + MP4_FREE + payload)


def mp4_mark(software: str) -> Callable[[Path], bool]:
    """An ``is_ours`` test for `refuse_foreign`: an MP4 that `mp4_marked` marked with ``software``."""
    payload = software.encode("latin-1")

    def test(path: Path) -> bool:
        with open(path, "rb") as handle:
            for kind, start, size in _mp4_boxes(path):
                if kind == MP4_FREE and size == len(payload):
                    handle.seek(start)
                    if handle.read(size) == payload:
                        return True
        return False
    return test

class OutputLock:
    """Held while a command writes ``path``: a second command for the same file is refused at once
    (`OutputError`) instead of both writing it and the last one winning. The lock is the hidden file
    ``.<name>.lock`` beside ``path``, locked by the operating system (released if the process dies) and
    removed when released."""

    def __init__(self, path: str | Path, command: str = "another run"):
        self.path = Path(path)
        self.lock_path = self.path.with_name(f".{self.path.name}.lock")
        self.command = command
        self._descriptor: int | None = None

    def __enter__(self) -> "OutputLock":
        self.lock_path.parent.mkdir(parents=True, exist_ok=True)
        while True:
            descriptor = os.open(self.lock_path, os.O_RDWR | os.O_CREAT, 0o644)  # unbuffered: nothing left to flush
            if not _try_lock(descriptor):
                holder = os.read(descriptor, 32).decode(errors="replace").strip()
                os.close(descriptor)
                raise OutputError(f"{self.command} is writing {self.path} now{f' (process {holder})' if holder else ''}: "
                                  f"wait for it to finish or choose another --out")
            try:  # the file may have been removed by the holder releasing it before we locked: lock the new one
                if os.fstat(descriptor).st_ino == os.stat(self.lock_path).st_ino:
                    break
            except FileNotFoundError:
                pass
            os.close(descriptor)
        self._descriptor = descriptor
        try:  # the holder's process ID, for the refusal's message; a full disk just leaves it out
            os.ftruncate(descriptor, 0)
            os.write(descriptor, str(os.getpid()).encode())
        except OSError:
            pass
        return self

    def __exit__(self, *exc) -> None:
        if self._descriptor is not None:
            self.lock_path.unlink(missing_ok=True)
            os.close(self._descriptor)  # closing releases the lock
            self._descriptor = None


def _try_lock(descriptor: int) -> bool:
    try:
        if fcntl is not None:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        else:  # pragma: no cover
            msvcrt.locking(descriptor, msvcrt.LK_NBLCK, 1)
    except OSError:
        return False
    return True
