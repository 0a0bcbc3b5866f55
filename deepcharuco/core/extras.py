"""Which optional packages (the extras of pyproject.toml) are installed: checked before a command starts its work,
so that a missing one is one line naming the package and the extra, not a traceback from a worker halfway."""

from __future__ import annotations

import importlib.util

from deepcharuco.core.errors import DeepCharucoError


def missing_packages(names: tuple[str, ...]) -> list[str]:
    """The import names among ``names`` that cannot be imported here (found without importing them)."""
    missing = []
    for name in names:
        try:
            found = importlib.util.find_spec(name) is not None
        except (ImportError, ValueError):  # a parent package missing, or a module entry set to None
            found = False
        if not found:
            missing.append(name)
    return missing


def missing_extra_message(command: str, names: tuple[str, ...], extra: str, note: str = "") -> str | None:
    """One line saying what ``command`` needs that is missing and how to install it, or None when all is there."""
    missing = missing_packages(names)
    if not missing:
        return None
    return (f"{command} needs {' and '.join(missing)}, which {'is' if len(missing) == 1 else 'are'} not installed: "
            f"pip install 'deepcharuco[{extra}]'{note}")


def require_extra(command: str, names: tuple[str, ...], extra: str, note: str = "") -> None:
    """`DeepCharucoError` (one line, exit code 2 from the commands) when a package of ``names`` is missing."""
    message = missing_extra_message(command, names, extra, note)
    if message is not None:
        raise DeepCharucoError(message)
