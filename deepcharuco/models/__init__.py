"""The two networks, their label encodings and their checkpoint files."""

from deepcharuco.models.charuconet import CELL, ChArUcoNet, ChArUcoNetConfig, fold_batch_norm
from deepcharuco.models.checkpoint import (
    CheckpointError, checkpoint_dict, load_charuconet, load_refinenet, read_checkpoint, save_bundle, save_checkpoint,
)
from deepcharuco.models.refinenet import RefineNet, RefineNetConfig, cell_to_offset, decode_offsets, offset_to_cell

__all__ = [
    "CELL", "ChArUcoNet", "ChArUcoNetConfig", "fold_batch_norm", "RefineNet", "RefineNetConfig", "cell_to_offset", "decode_offsets",
    "offset_to_cell", "CheckpointError", "checkpoint_dict", "load_charuconet", "load_refinenet", "read_checkpoint",
    "save_bundle", "save_checkpoint",
]
