"""Networks as ONNX files, with what the detector needs to use them: a bundle the runtime reads without PyTorch.

A bundle is a folder ``NAME.onnx/`` beside the weights ``NAME.pt`` it was exported from::

    bundle.json               format, the board, the score threshold, which heads were trained, the source
                              weights' file name and the sha256 of ChArUcoNet's weights (as loaded)
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
    fix = f"export it again (deepcharuco export --bundle --weights {path.with_suffix('.pt').name})"
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
    return OnnxBundle(path, board, meta, models)
