"""Networks: ChArUcoNet, RefineNet and the bit reader, their label encodings, checkpoint files, ONNX bundles and
the runners that execute them (PyTorch or ONNX Runtime).

Imports `deepcharuco.core` and `deepcharuco.boards`.

The networks and checkpoints need PyTorch; the label encodings (`cells`) and RefineNet's offset decoding
(`offsets`) do not, so the names here are loaded on first use: importing `deepcharuco.networks.cells` does not
import PyTorch.
"""

from typing import TYPE_CHECKING

from deepcharuco.core.lazy import lazy_exports

_WHERE = {
    "CELL": "cells", "ChArUcoNet": "charuconet", "ChArUcoNetConfig": "charuconet", "fold_batch_norm": "charuconet",
    "RefineNet": "refinenet", "RefineNetConfig": "refinenet", "cell_to_offset": "refinenet",
    "decode_offsets": "refinenet", "offset_to_cell": "refinenet", "CheckpointError": "checkpoint",
    "checkpoint_dict": "checkpoint", "load_charuconet": "checkpoint", "load_refinenet": "checkpoint",
    "read_checkpoint": "checkpoint", "save_bundle": "checkpoint", "save_checkpoint": "checkpoint",
}

__all__ = list(_WHERE)
__getattr__, __dir__ = lazy_exports(__name__, _WHERE)

if TYPE_CHECKING:
    from deepcharuco.networks.cells import CELL
    from deepcharuco.networks.charuconet import ChArUcoNet, ChArUcoNetConfig, fold_batch_norm
    from deepcharuco.networks.checkpoint import (CheckpointError, checkpoint_dict, load_charuconet, load_refinenet,
                                                 read_checkpoint, save_bundle, save_checkpoint)
    from deepcharuco.networks.refinenet import (RefineNet, RefineNetConfig, cell_to_offset, decode_offsets,
                                                offset_to_cell)
