"""The layers point one way: the runtime (deepcharuco/) imports nothing from evaluate/, train/ or datagen/; inside
it, each subpackage imports only those below it (`SUBPACKAGES`, docs/architecture.md); and no module imports, at
the top or inside a function, one that imports it back (no cycles)."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("deepcharuco", "evaluate", "train", "datagen")
# The runtime's subpackages, bottom to top: each may import those before it, never one after it.
SUBPACKAGES = ("core", "boards", "geometry", "networks", "detection", "calibration", "cli")
# Modules directly in deepcharuco/: the public API and the documented entry points, above every subpackage.
TOP = {"deepcharuco", "deepcharuco.__main__", "deepcharuco.detect", "deepcharuco.calibrate"}


def import_graph() -> dict[str, set[str]]:
    """Module -> the project's modules it imports (``import a.b``, ``from a import b`` of a module, anywhere in it)."""
    modules = {}
    for path in (p for package in PACKAGES for p in (ROOT / package).rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    graph = {name: set() for name in modules}
    for name, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets = [node.module] + [f"{node.module}.{alias.name}" for alias in node.names]
            else:
                continue
            graph[name].update(t for t in targets if t in modules and t != name)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, iterative)."""
    index, low, on_stack, stack, found, counter = {}, {}, set(), [], [], 0
    for start in graph:
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_the_runtime_imports_no_other_layer():
    graph = import_graph()
    assert "deepcharuco.cli.detect" in graph and "evaluate.report" in graph  # the graph sees the project
    crossing = sorted((m, t) for m, targets in graph.items() if m.startswith("deepcharuco")
                      for t in targets if not t.startswith("deepcharuco"))
    assert crossing == []


def test_no_import_cycles():
    assert cycles(import_graph()) == []


def layer(module: str) -> int:
    """The rank of a runtime module: its subpackage's place in `SUBPACKAGES`, or above them all for `TOP` and
    the examples' script."""
    if module in TOP or module.startswith("deepcharuco.examples."):  # examples/make_examples.py: a script
        return len(SUBPACKAGES)
    parts = module.split(".")
    assert len(parts) >= 2 and parts[1] in SUBPACKAGES, f"{module} is in no subpackage of {SUBPACKAGES}"
    return SUBPACKAGES.index(parts[1])


def upward_imports(graph: dict[str, set[str]]) -> list[tuple[str, str]]:
    """Runtime imports from a lower subpackage into a higher one, (importer, imported)."""
    return sorted((m, t) for m, targets in graph.items() if m.startswith("deepcharuco")
                  for t in targets if t.startswith("deepcharuco") and layer(t) > layer(m))


def test_every_runtime_module_is_in_a_subpackage():
    loose = sorted(m for m in import_graph() if m.startswith("deepcharuco") and m not in TOP
                   and m.split(".")[1] not in SUBPACKAGES + ("examples",))
    assert loose == []


def test_subpackages_import_only_those_below_them():
    assert upward_imports(import_graph()) == []


def test_the_layer_check_sees_an_import_up():
    # the old layout's kind of mistake: a file helper importing the command line (files.py -> cli.py)
    graph = {"deepcharuco.core.files": {"deepcharuco.cli.common"}, "deepcharuco.cli.common": {"deepcharuco.core.errors"},
             "deepcharuco.core.errors": set()}
    assert upward_imports(graph) == [("deepcharuco.core.files", "deepcharuco.cli.common")]


def test_the_cycle_finder_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_every_public_name_resolves():
    """The package's and each subpackage's ``__all__`` (lazy ones included) give real objects, listed by ``dir``."""
    import importlib

    import deepcharuco

    assert {"Detector", "BoardSpec", "OpenCVDetector", "BoardTracker", "read_camera", "detect_all"} <= set(deepcharuco.__all__)
    for name in ("deepcharuco", *(f"deepcharuco.{sub}" for sub in SUBPACKAGES)):
        package = importlib.import_module(name)
        for public in package.__all__:
            assert getattr(package, public) is not None, (name, public)
            assert public in dir(package), (name, public)
