"""Names a package hands on from its modules, imported on first use.

A package's ``__init__`` maps each public name to the module that defines it; ``lazy_exports`` gives the
module-level ``__getattr__`` and ``__dir__`` (PEP 562) that import that module when the name is first asked
for. So ``import deepcharuco.networks.cells`` does not import PyTorch through ``networks/__init__``, and
``from deepcharuco.detection import Detector`` still works. Type checkers and IDEs see the same names
through each ``__init__``'s ``if TYPE_CHECKING:`` imports.
"""

from __future__ import annotations

import importlib
from typing import Any, Callable


def lazy_exports(package: str, where: dict[str, str]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """``(__getattr__, __dir__)`` for ``package``, whose public ``name`` lives in module ``package.where[name]``.

    Example:
        >>> getattr_, dir_ = lazy_exports("deepcharuco.geometry", {"Pose": "pose"})
        >>> getattr_("Pose").__name__
        'Pose'
        >>> "Pose" in dir_()
        True
    """

    def __getattr__(name: str) -> Any:
        if name in where:
            return getattr(importlib.import_module(f"{package}.{where[name]}"), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__() -> list[str]:
        return sorted(set(where) | set(importlib.import_module(package).__dict__))

    return __getattr__, __dir__
