"""The run folder's records: JSON written atomically, read back without trusting it, the stage names in file
names, and the time stamps in them."""

from __future__ import annotations

import datetime as dt
import json
import re
import shutil
from pathlib import Path

from deepcharuco.core.files import write_atomic


def now() -> str:
    """The time in UTC to the second, ISO 8601: 2026-11-27T17:30:00+00:00."""
    return dt.datetime.now(dt.timezone.utc).replace(microsecond=0).isoformat()


def write_json(path: Path, data) -> None:
    """Write atomically: a kill leaves the previous file or the new one, never half of one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, json.dumps(data, indent=1, default=str) + "\n")


def read_json(path: Path):
    """The JSON in ``path``; None when it is missing, empty, cut off or not JSON."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def slug(name: str) -> str:
    """A stage's or board's name as a file name: lower case, each run of other characters one '-'."""
    return re.sub(r"[^a-z0-9_.-]+", "-", name.lower()).strip("-")


def remove_tree(path: Path) -> None:
    """Remove a scratch or staging folder, whatever it holds; a missing one is no error."""
    shutil.rmtree(path, ignore_errors=True)
