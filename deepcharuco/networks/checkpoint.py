"""Checkpoint files of the two networks: weights plus everything needed to use them.

A checkpoint is a ``torch.save`` dict:

    format: "deepcharuco-checkpoint", format_version: 1
    kind: "charuconet" | "refinenet"
    config: the architecture (ChArUcoNetConfig / RefineNetConfig as a dict)
    board: BoardSpec dict (ChArUcoNet only: its ID head is that board's)
    input_size: [W, H] it was trained at (ChArUcoNet), [24, 24] (RefineNet)
    state_dict: the weights
    training: free-form (step, metrics, command ...)
    threshold: optional, ChArUcoNet: the score threshold chosen on validation frames
    heads: optional, ChArUcoNet: "points" when only the point head was trained (a family model, trained
        on many boards: its ID head means nothing, so every board is decoded by its markers); absent
        when both heads were trained

A "bundle" holds both: {"format": ..., "kind": "bundle", "charuconet": {...}, "refinenet": {...}}.
Loading checks all of it and says what is wrong and what to do.
"""

from __future__ import annotations

from pathlib import Path

import torch

from deepcharuco.boards.board import BoardSpec
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.networks.charuconet import ChArUcoNet, ChArUcoNetConfig, fold_batch_norm
from deepcharuco.networks.onnx_bundle import PointsOnlyBoard  # noqa: F401 (defined where the runtime reads it without torch)
from deepcharuco.networks.refinenet import RefineNet, RefineNetConfig

FORMAT = "deepcharuco-checkpoint"
FORMAT_VERSION = 1
HEADS = ("all", "points")  # which ChArUcoNet heads a run trains: both, or the point head alone


class CheckpointError(DeepCharucoError, ValueError):
    """A weights file that cannot be used as asked."""


def checkpoint_dict(model: torch.nn.Module, board: BoardSpec | None = None, input_size: tuple[int, int] | None = None,
                    training: dict | None = None, heads: str = "all") -> dict:
    """The dict to ``torch.save`` for ``model`` (a ChArUcoNet needs ``board``). ``heads="points"``: only
    ChArUcoNet's point head was trained, recorded so that loading never trusts its ID head."""
    if heads not in HEADS:
        raise CheckpointError(f"heads must be one of {HEADS}, got {heads!r}")
    if isinstance(model, ChArUcoNet):
        if board is None or board.num_corners != model.config.num_corners:
            raise CheckpointError("a ChArUcoNet checkpoint needs the BoardSpec whose corners its ID head classifies")
        kind = "charuconet"
    elif isinstance(model, RefineNet):
        kind, input_size = "refinenet", (24, 24)
    else:
        raise CheckpointError(f"not a ChArUcoNet or RefineNet: {type(model).__name__}")
    if heads != "all" and kind != "charuconet":
        raise CheckpointError(f"heads={heads!r} applies to ChArUcoNet; a {kind} has one head")
    state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    if isinstance(board, PointsOnlyBoard):
        board = board.plain()
    data = {"format": FORMAT, "format_version": FORMAT_VERSION, "kind": kind, "config": model.config.to_dict(),
            "board": board.to_dict() if board else None, "input_size": list(input_size) if input_size else None,
            "state_dict": state, "training": training or {}}
    if heads != "all":  # absent in both-heads checkpoints, so their files stay as they always were
        data["heads"] = heads
    return data


def id_head_trained(data: dict) -> bool:
    """Whether a ChArUcoNet checkpoint's (or a bundle part's) ID head was trained (not a points-only run)."""
    return data.get("heads", "all") != "points"


def save_checkpoint(path: str | Path, model: torch.nn.Module, **kwargs) -> Path:
    """Write a checkpoint atomically (temporary file + rename)."""
    return save_atomically(checkpoint_dict(model, **kwargs), path)


def save_atomically(data: dict, path: str | Path) -> Path:
    """``torch.save`` to a temporary name, then rename: a reader never sees half a file, and a failed
    write (a full disk) leaves the previous file as it was and no temporary behind."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp")
    try:
        torch.save(data, temporary)
        temporary.replace(path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
    return path


def save_bundle(path: str | Path, charuconet: str | Path, refinenet: str | Path, note: dict | None = None,
                threshold: float | None = None, geometry: str | None = None, input_white: float | None = None
                ) -> Path:
    """Both networks' checkpoints in one shippable file, written atomically.

    Training state that only resuming needs (optimizer, AMP scaler) is dropped, which is most of a
    checkpoint's size; the step, the run's settings and its validation metrics are kept under
    ``training``, and ``note`` (free-form: commands, data, hardware) under ``note``. ``threshold``, the
    operating point chosen on validation frames, becomes the ChArUcoNet part's ``threshold``, the
    `Detector`'s default; ``geometry`` (`deep_detector.DECODINGS`), its ``geometry``: how `Detector` decodes the
    weights' own board when not told (else "repair" where the ID head was trained); ``input_white``, its
    ``input_white``: the grey ChArUcoNet's dim inputs are brightened to (`onnx_bundle.input_white`)."""
    parts = {}
    for kind, source in (("charuconet", charuconet), ("refinenet", refinenet)):
        data = read_checkpoint(source, kind)
        training = {k: v for k, v in data.get("training", {}).items() if k not in ("optimizer", "scaler")}
        parts[kind] = {k: v for k, v in data.items() if k not in ("format", "format_version")} | {"training": training}
    if threshold is not None:
        if not 0.0 < threshold < 1.0:
            raise CheckpointError(f"threshold {threshold} is not a score in (0, 1)")
        parts["charuconet"]["threshold"] = float(threshold)
    if geometry is not None:
        if geometry not in ("repair", "filter", "none", "markers"):
            raise CheckpointError(f"geometry {geometry!r} is none of repair, filter, none, markers")
        parts["charuconet"]["geometry"] = geometry
    if input_white is not None:
        if not 0.0 < input_white <= 1.0:
            raise CheckpointError(f"input_white {input_white} is not a grey in (0, 1]")
        parts["charuconet"]["input_white"] = float(input_white)
    return save_atomically({"format": FORMAT, "format_version": FORMAT_VERSION, "kind": "bundle", **parts,
                             "note": note or {}}, path)


def read_checkpoint(path: str | Path, kind: str) -> dict:
    """The ``kind`` ("charuconet" / "refinenet") checkpoint in ``path`` (a checkpoint or a bundle), validated."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"weights file {path} does not exist")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # pickle, zip and torch errors all mean "not our file"
        raise CheckpointError(f"{path} is not a readable PyTorch checkpoint ({type(error).__name__}: {error})") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a Deep ChArUco checkpoint (no format={FORMAT!r}); "
                              f"train one with python -m train.{kind}")
    if data.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"{path} has checkpoint format {data.get('format_version')}, this code reads {FORMAT_VERSION}")
    if data.get("kind") == "bundle":
        if kind not in data:
            raise CheckpointError(f"the bundle {path} holds no {kind}")
        data = {**data[kind], "format": FORMAT, "format_version": FORMAT_VERSION}
    if data.get("kind") != kind:
        raise CheckpointError(f"{path} holds a {data.get('kind')} checkpoint, a {kind} was expected")
    return data


def load_charuconet(path: str | Path, board: BoardSpec | None = None) -> tuple[ChArUcoNet, BoardSpec, dict]:
    """(network in eval mode, batch norm folded, its board, the checkpoint) from ``path``.

    ``board``, when given, must have the layout the ID head was trained for (`BoardSpec.same_layout`:
    the same board printed at another size, inverted or mirrored fits); the board returned is then
    ``board`` itself, so poses come out in its size.

    A points-only checkpoint (``heads: "points"``, a family model) fits any ``board``; the board
    returned is then a `PointsOnlyBoard` (the stored one), whose layout matches no board, so a
    `Detector` decodes every board, its default one included, by markers (geometry "markers")."""
    data = read_checkpoint(path, "charuconet")
    trained_for = BoardSpec.from_dict(data["board"])
    if not id_head_trained(data):
        trained_for = PointsOnlyBoard(**trained_for.to_dict())
    elif board is not None:
        if not board.same_layout(trained_for):
            raise CheckpointError(
                f"{path}'s ID head was trained for {trained_for}, whose layout (grid, dictionary, legacy, "
                f"marker/square ratio) differs from {board}: use Detector(board=...) without these weights' "
                "ID head (geometry='markers', any board), or train a ChArUcoNet on renders of this board "
                "(python -m datagen.render --board B.yaml, then python -m train.charuconet)")
        trained_for = board
    model = ChArUcoNet(ChArUcoNetConfig.from_dict(data["config"]))
    _load_state(model, data, path)
    return fold_batch_norm(model.eval()), trained_for, data


def load_refinenet(path: str | Path) -> tuple[RefineNet, dict]:
    """(network in eval mode, batch norm folded, the checkpoint) from ``path``."""
    data = read_checkpoint(path, "refinenet")
    model = RefineNet(RefineNetConfig.from_dict(data["config"]))
    _load_state(model, data, path)
    return fold_batch_norm(model.eval()), data


def _load_state(model: torch.nn.Module, data: dict, path: Path) -> None:
    try:
        model.load_state_dict(data["state_dict"])
    except RuntimeError as error:
        first = str(error).strip().splitlines()[:3]
        raise CheckpointError(f"the weights in {path} do not fit the architecture it declares "
                              f"({data['config']}): {' '.join(first)}") from None
