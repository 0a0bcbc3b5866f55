"""The ``Example:`` blocks in the runtime's docstrings run, and give what they show."""

import doctest
import importlib

import pytest

from conftest import ROOT

# Every runtime module whose docstrings hold an example (a ``>>>`` line), found from the source.
MODULES = sorted(
    ".".join(path.relative_to(ROOT).with_suffix("").parts)
    for path in (ROOT / "deepcharuco").rglob("*.py")
    if ">>> " in path.read_text() and path.name != "__init__.py"
)


def test_the_examples_are_found():
    assert {"deepcharuco.core.checks", "deepcharuco.geometry.pose"} <= set(MODULES)


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples_run(name):
    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0 and result.failed == 0
