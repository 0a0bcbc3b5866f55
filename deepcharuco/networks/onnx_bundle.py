"""Networks as ONNX files, with what the detector needs to use them: a bundle the runtime reads without PyTorch.

A bundle is a folder ``NAME.onnx/`` beside the weights ``NAME.pt`` it was exported from::

    bundle.json               format, the board, the score threshold, which heads were trained, the source
                              weights' file name and the sha256 of ChArUcoNet's weights (as loaded); optionally
                              ``geometry``: how `Detector` decodes the weights' own board when not told, and
                              ``input_white``: the grey (0-1] ChArUcoNet's input is brightened to where its 99th
                              percentile lies below it (`input_white`); optionally ``refinenet``: where
                              RefineNet came from another checkpoint than the weights (its path, sha256 and
                              architecture; ``python -m train.swap_refinenet``)
    charuconet.onnx           ChArUcoNet, both heads (only where the ID head was trained)
    charuconet_points.onnx    ChArUcoNet's point head alone (boards read by their markers)
    charuconet_int8.onnx      the int8 ChArUcoNet the weights carry, where they carry one
    refinenet.onnx            RefineNet (where the weights hold one)

`deepcharuco.cli.export.write_onnx_bundle` writes one (``deepcharuco export --bundle``; the
trainers' ``train.bundle`` and ``train.pipeline`` write it beside every ``detector.pt``). The models are
exported exactly as `deepcharuco.networks.runtime` exports them in memory, so a `Detector` runs the same networks
with PyTorch installed or not.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field, fields
from pathlib import Path

from deepcharuco.boards.board import BoardSpec
from deepcharuco.core.errors import DeepCharucoError

FORMAT = 1
META_FILE = "bundle.json"
MODELS = ("charuconet.onnx", "charuconet_points.onnx", "charuconet_int8.onnx", "refinenet.onnx")


class BundleError(DeepCharucoError, ValueError):
    """A damaged or incomplete ONNX bundle."""


@dataclass(frozen=True)
class PointsOnlyBoard(BoardSpec):
    """The board stored with a ChArUcoNet whose ID head was never trained (``heads: "points"``).

    It is a real board (the default a `Detector` without ``board=`` looks for), but no board has its
    layout, itself included: whoever compares layouts to decide whether the ID head applies
    (`Detector`'s "repair" for its own board) is told it does not, and decodes by markers."""

    @property
    def layout(self) -> tuple:
        return ("untrained ID head", *super().layout)

    def same_layout(self, other: "BoardSpec") -> bool:
        return False

    def plain(self) -> BoardSpec:
        """The same board as an ordinary `BoardSpec` (to render it, save it, compare it with shards')."""
        return BoardSpec(**{f.name: getattr(self, f.name) for f in fields(BoardSpec)})


@dataclass
class OnnxBundle:
    """A read bundle: ``board`` the weights' board (a `PointsOnlyBoard` when the ID head is untrained),
    ``meta`` bundle.json's content, ``models`` file name -> serialized ONNX."""

    path: Path
    board: BoardSpec
    meta: dict
    models: dict[str, bytes] = field(default_factory=dict)

    @property
    def id_head(self) -> bool:
        return self.meta.get("heads", "all") != "points"


def bundle_path(weights: str | Path) -> Path:
    """Where the bundle of the weights file ``weights`` (``NAME.pt``) lies: ``NAME.onnx``."""
    return Path(weights).with_suffix(".onnx")


def is_bundle(path: str | Path) -> bool:
    return Path(path).is_dir() and (Path(path) / META_FILE).is_file()


def read_bundle(path: str | Path) -> OnnxBundle:
    """Read the bundle folder ``path``; `BundleError` naming the file and the fix when it is damaged."""
    path = Path(path)
    fix = bundle_fix(path)
    try:
        meta = json.loads((path / META_FILE).read_text())
        board = BoardSpec.from_dict(meta["board"], source=str(path / META_FILE))
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise BundleError(f"{path / META_FILE} is damaged ({type(error).__name__}: {error}): {fix}") from None
    if meta.get("format") != FORMAT:
        raise BundleError(f"{path} is bundle format {meta.get('format')}, this version reads {FORMAT}: {fix}")
    if meta.get("heads") == "points":
        board = PointsOnlyBoard(**board.to_dict())
    models = {name: (path / name).read_bytes() for name in MODELS if (path / name).is_file()}
    if "charuconet_points.onnx" not in models or (meta.get("heads") != "points" and "charuconet.onnx" not in models):
        raise BundleError(f"{path} lacks its ChArUcoNet model(s): {fix}")
    for name, data in models.items():
        if not data:
            raise BundleError(f"{path / name} is empty: {fix}")
    recorded = meta.get("models_sha256") or {}  # bundles exported before it was recorded have none
    for name, data in models.items():
        if name in recorded and hashlib.sha256(data).hexdigest() != recorded[name]:
            raise BundleError(f"{path / name} is not the model exported into this bundle ({len(data)} bytes, another "
                              f"sha256 than bundle.json records: truncated, damaged or replaced): {fix}")
    return OnnxBundle(path, board, meta, models)


# The outputs each model of a bundle names (`deepcharuco.networks.runtime.float_onnx`): a model file put in another's place
# (refinenet.onnx as charuconet.onnx) loads, and would fail only at its first run.
OUTPUTS = {"charuconet.onnx": ["point_logits", "id_logits"], "charuconet_points.onnx": ["point_logits"],
           "refinenet.onnx": ["logits"]}


def file_sha256(path: str | Path) -> str:
    """sha256 of a file's bytes (read in 1 MiB blocks)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def check_exported_from(bundle: OnnxBundle, weights: str | Path) -> None:
    """`BundleError` where ``bundle`` (found beside ``weights``, read in its place without PyTorch) was exported from
    other bytes of ``weights`` than it holds now (retrained or replaced since): bundles record the weights file's
    sha256 (``weights_file_sha256``; PyTorch's ``weights_sha256`` of the loaded network needs PyTorch to check)."""
    recorded = bundle.meta.get("weights_file_sha256")
    if recorded and Path(weights).is_file() and file_sha256(weights) != recorded:
        raise BundleError(f"{bundle.path} was exported from another {Path(weights).name} than the one beside it "
                          f"(retrained or replaced since): {bundle_fix(bundle.path)} where PyTorch is installed")


def input_white(meta: dict, source: str | Path) -> float | None:
    """A checkpoint's or bundle's ``input_white`` (``meta``: its ChArUcoNet part or bundle.json; ``source``: where it
    was read, for the message), or None: the grey in (0, 1] that ChArUcoNet's input is brightened to where its 99th
    percentile lies below it (`deepcharuco.detection.levels.network_input`). Distilled networks whose confidences fade
    in near darkness carry it (the shipped fast networks: docs/detector.md, "The fast networks' input brightened")."""
    value = meta.get("input_white")
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 < value <= 1.0:
        raise BundleError(f"{source}: input_white {value!r} is not a grey in (0, 1]: give one there, or bundle the "
                          f"weights again (python -m train.bundle ... --input-white GREY)")
    return float(value)


def bundle_fix(path: Path) -> str:
    return f"export it again (deepcharuco export --bundle --weights {Path(path).with_suffix('.pt').name})"


def checked_runner(bundle: OnnxBundle, names: list[str], make):
    """``make()`` (an `OnnxRunner` over the bundle's models ``names``: ChArUcoNet's, then RefineNet's if any), or
    `BundleError` naming the file that ONNX Runtime cannot load (an empty or truncated file; its own exceptions,
    e.g. ``InvalidProtobuf``) or whose outputs are another model's."""
    from deepcharuco.networks.onnx_runner import _session

    try:
        runner = make()
    except Exception as error:  # noqa: BLE001 - ONNX Runtime's exceptions share no public base class
        if not type(error).__module__.startswith("onnxruntime"):
            raise
        for name in names:  # which one: each loaded alone (the error path only)
            try:
                _session(bundle.models[name], 1)
            except Exception as failed:  # noqa: BLE001
                reason = (str(failed).splitlines() or [""])[0][:160]
                raise BundleError(f"{bundle.path / name} cannot be loaded by ONNX Runtime ({type(failed).__name__}: "
                                  f"{reason}): {bundle_fix(bundle.path)}") from None
        raise
    sessions = [runner.charuconet_session] + ([runner.refinenet_session] if len(names) > 1 else [])
    for name, session in zip(names, sessions):
        outputs = [output.name for output in session.get_outputs()]
        expected = OUTPUTS.get(name, OUTPUTS["charuconet_points.onnx"])  # int8: at least the point head
        if outputs[:len(expected)] != expected:
            raise BundleError(f"{bundle.path / name} is not a {name[:-5]} model (its outputs are {', '.join(outputs)}, "
                              f"not {', '.join(expected)}): another model's file in its place? {bundle_fix(bundle.path)}")
    return runner
