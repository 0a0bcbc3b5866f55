"""RefineNet's output grid and its decoding to sub-pixel offsets, in numpy (no PyTorch needed).

Sub-pixel convention (OpenCV's: pixel centres at integers). The central 8x8 pixels of a 24x24 patch are
8..15, covering positions [7.5, 15.5) on each axis. Grid cell j (0..63) covers [7.5 + j/8, 7.5 + (j+1)/8);
a corner at ``offset`` is cell ``floor((offset - 7.5) * 8)`` and the cell decodes to its centre
``7.5 + (j + 0.5) / 8``, so encode->decode errs by at most 1/16 px per axis.
"""

from __future__ import annotations

import numpy as np

from deepcharuco.networks.cells import as_array

PATCH = 24
GRID = 64  # 8 pixels x 8 sub-pixel steps
CENTRE_LOW = 7.5  # the central 8x8 region spans [7.5, 15.5) in patch pixel coordinates


def cell_centres(index: np.ndarray) -> np.ndarray:
    """(...) class indices -> (..., 2) float32 offsets (x, y) of the cell centres in patch pixels."""
    index = np.asarray(index, np.int64)
    return (np.stack([index % GRID, index // GRID], axis=-1).astype(np.float32) + np.float32(0.5)) / np.float32(8) \
        + np.float32(CENTRE_LOW)


def soft_argmax_offsets(logits, soft_radius: int = 2) -> np.ndarray:
    """(B, 4096) logits (numpy, or a PyTorch tensor) -> (B, 2) float32 offsets: the argmax cell, then
    (``soft_radius`` > 0) the probability-weighted mean of the cell centres within that many cells of it
    (soft-argmax); the window's probabilities renormalised are a softmax over its logits alone."""
    values = as_array(logits)
    argmax = values.argmax(axis=1)
    if soft_radius <= 0:
        return cell_centres(argmax)
    row, col = argmax // GRID, argmax % GRID
    steps = np.arange(-soft_radius, soft_radius + 1)
    rows = np.clip(row[:, None] + steps[None, :], 0, GRID - 1)  # (B, K)
    cols = np.clip(col[:, None] + steps[None, :], 0, GRID - 1)
    window = values.reshape(-1, GRID, GRID)[np.arange(len(values))[:, None, None], rows[:, :, None], cols[:, None, :]]
    weights = np.exp(window - window.max(axis=(1, 2), keepdims=True))
    weights /= weights.sum(axis=(1, 2), keepdims=True)  # (B, K, K)
    x = (weights.sum(axis=1) * cols).sum(axis=1)
    y = (weights.sum(axis=2) * rows).sum(axis=1)
    return ((np.stack([x, y], axis=1) + 0.5) / 8 + CENTRE_LOW).astype(np.float32)
