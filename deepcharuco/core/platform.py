"""What the operating system says: why an OS call failed and what the user can do, and how many CPUs this
process may use."""

from __future__ import annotations

import errno
import os

# What a user can do about an OSError, by errno (the rest get the generic advice).
_ADVICE = {
    errno.ENOSPC: "free some space or choose another --out",
    errno.EDQUOT: "free some space or choose another --out",
    errno.EFBIG: "the file system refused a file this large: choose another --out",
    errno.EACCES: "choose a writable --out or fix the permissions",
    errno.EPERM: "choose a writable --out or fix the permissions",
    errno.EROFS: "the file system is read-only: choose another --out",
    errno.ENOTDIR: "a path component is a file, not a folder: choose another path",
    errno.EISDIR: "a folder is in the way: choose another path",
}


def explain_os_error(error: OSError) -> str:
    """Why an OSError happened and what to do: ``reason (advice)``."""
    advice = _ADVICE.get(error.errno, "check the path, its permissions and the free space")
    return f"{error.strerror or error} ({advice})"


def describe_os_error(error: OSError) -> str:
    """One line naming what failed (the file, when known), why, and what to do."""
    where = f" {error.filename}" if error.filename else ""
    return f"cannot access{where}: {explain_os_error(error)}"


def available_cpus() -> int:
    """CPUs this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
