"""The two networks, their label encodings and their checkpoint files.

The networks and checkpoints need PyTorch; the label encodings (`cells`) and RefineNet's offset decoding
(`offsets`) do not, so the names here are loaded on first use: importing `deepcharuco.models.cells` does not
import PyTorch.
"""

import importlib

_WHERE = {
    "CELL": "cells", "ChArUcoNet": "charuconet", "ChArUcoNetConfig": "charuconet", "fold_batch_norm": "charuconet",
    "RefineNet": "refinenet", "RefineNetConfig": "refinenet", "cell_to_offset": "refinenet",
    "decode_offsets": "refinenet", "offset_to_cell": "refinenet", "CheckpointError": "checkpoint",
    "checkpoint_dict": "checkpoint", "load_charuconet": "checkpoint", "load_refinenet": "checkpoint",
    "read_checkpoint": "checkpoint", "save_bundle": "checkpoint", "save_checkpoint": "checkpoint",
}

__all__ = list(_WHERE)


def __getattr__(name: str):
    if name in _WHERE:
        return getattr(importlib.import_module(f"deepcharuco.models.{_WHERE[name]}"), name)
    raise AttributeError(f"module 'deepcharuco.models' has no attribute {name!r}")
