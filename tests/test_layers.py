"""evaluate/'s subpackages and train.pipeline's modules import one way, bottom first (train/pipeline/__init__.py
gives its order):

    evaluate.paper -> evaluate.captures -> evaluate.speed -> evaluate.calibration -> evaluate (report, documents)

a module may import from its own layer and the layers before it, never from one after it. `test_architecture`
builds the import graph (every ``import``, at the top or inside a function) and checks that there are no cycles."""

from test_architecture import import_graph

EVALUATE_LAYERS = ("evaluate.paper", "evaluate.captures", "evaluate.speed", "evaluate.calibration", "evaluate")


def layer_of(module: str, layers: tuple[str, ...]) -> int | None:
    """The index of the longest of ``layers`` that ``module`` is or lies in; None outside them all."""
    matches = [i for i, name in enumerate(layers) if module == name or module.startswith(name + ".")]
    return max(matches, key=lambda i: len(layers[i])) if matches else None


def upward_imports(graph: dict[str, set[str]], layers: tuple[str, ...]) -> list[tuple[str, str]]:
    """(module, imported) for each import from a layer into a later one."""
    found = []
    for module, targets in graph.items():
        own = layer_of(module, layers)
        if own is None:
            continue
        found += [(module, t) for t in sorted(targets) if (other := layer_of(t, layers)) is not None and other > own]
    return sorted(found)


def test_evaluate_imports_point_down():
    graph = import_graph()
    assert {"evaluate.paper.protocols", "evaluate.paper.autolabel", "evaluate.speed.machine",
            "evaluate.calibration.rig_eval", "evaluate.report"} <= set(graph)  # the graph sees the layout
    assert upward_imports(graph, EVALUATE_LAYERS) == []


def test_the_layer_check_finds_an_upward_import():
    # The mistake the layout had to undo: `python -m evaluate.captures` naming its figures with the report's helper.
    graph = {"evaluate.captures.__main__": {"evaluate.documents", "evaluate.paper.figures"},
             "evaluate.paper.figures": {"evaluate.paper.protocols"}, "evaluate.documents": {"evaluate.captures"},
             "evaluate.calibration.rig_eval": {"evaluate.speed.realistic"}, "datagen.lens": set()}
    assert upward_imports(graph, EVALUATE_LAYERS) == [("evaluate.captures.__main__", "evaluate.documents")]
    assert layer_of("evaluate.paper", EVALUATE_LAYERS) == 0 and layer_of("evaluate.report", EVALUATE_LAYERS) == 4
    assert layer_of("evaluate_more.x", EVALUATE_LAYERS) is None


PIPELINE_LAYERS = tuple(f"train.pipeline.{name}" for name in (
    "records", "plan", "rates", "checks", "evaluation", "stages", "card", "run", "cluster", "kubernetes", "command")) + ("train.pipeline",)


def test_the_pipeline_modules_import_in_their_order():
    graph = import_graph()
    assert set(PIPELINE_LAYERS) <= set(graph)  # every module of train/pipeline/ is named in the order
    assert {m for m in graph if m.startswith("train.pipeline.")} <= set(PIPELINE_LAYERS) | {"train.pipeline.__main__"}
    assert upward_imports(graph, PIPELINE_LAYERS) == []
