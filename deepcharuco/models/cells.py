"""ChArUcoNet's per-cell labels: corners <-> (point class, ID class) per 8x8 cell.

Encoding (training targets). A corner at (x, y) (OpenCV pixels) falls on pixel
(round(x), round(y)); its cell is that pixel // 8 and its point class the pixel's place in
the cell, ``(py % 8) * 8 + (px % 8)``. Cells without a visible corner get the dustbin, 64
for points and N for IDs. Should two corners share a cell (a tiny, far board), the one with
the lower ID is kept.

Decoding (inference). Per cell: point confidence = 1 - P(point dustbin), position = the most
likely of the 64 pixels, ID = the most likely of the N IDs, score = point confidence x
P(ID). Then for each ID the best-scoring cell is kept if its score reaches ``threshold``.
"""

from __future__ import annotations

import numpy as np
import torch

from deepcharuco.models.charuconet import CELL


def encode_cells(corners: np.ndarray, visible: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(C, 2) corners + (C,) visibility -> point labels and ID labels, both (H/8, W/8) int64."""
    rows, cols = height // CELL, width // CELL
    num_corners = len(corners)
    points = np.full((rows, cols), CELL * CELL, dtype=np.int64)
    ids = np.full((rows, cols), num_corners, dtype=np.int64)
    for corner_id in np.flatnonzero(visible)[::-1]:  # lower IDs written last: they win a shared cell
        x, y = corners[corner_id]
        if not (np.isfinite(x) and np.isfinite(y)):
            continue
        px, py = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
        if not (0 <= px < cols * CELL and 0 <= py < rows * CELL):
            continue
        points[py // CELL, px // CELL] = (py % CELL) * CELL + (px % CELL)
        ids[py // CELL, px // CELL] = corner_id
    return points, ids


def decode_cells(point_logits: torch.Tensor, id_logits: torch.Tensor, threshold: float = 0.3
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One image's logits (65, Hc, Wc) and (N+1, Hc, Wc) -> (ids (M,), pixels (M, 2) float32 x,y, scores (M,)).

    At most one detection per ID: the best-scoring cell (see the module docstring)."""
    point_prob = torch.softmax(point_logits.float(), dim=0)
    id_prob = torch.softmax(id_logits.float(), dim=0)
    confidence = 1.0 - point_prob[-1]
    position = point_prob[:-1].argmax(dim=0)  # (Hc, Wc) in 0..63
    id_score, corner_id = id_prob[:-1].max(dim=0)
    score = (confidence * id_score).flatten()
    corner_id = corner_id.flatten()
    num_corners = id_logits.shape[0] - 1
    # Best cell per ID: visit cells above the threshold by falling score, keep each ID's first.
    above = torch.nonzero(score >= threshold).flatten()
    order = above[torch.argsort(score[above], descending=True)].tolist()
    best: dict[int, int] = {}  # ID -> its best cell
    for cell in order:
        best.setdefault(int(corner_id[cell]), cell)
        if len(best) == num_corners:
            break
    if not best:
        return np.zeros(0, np.int64), np.zeros((0, 2), np.float32), np.zeros(0, np.float32)
    cols = point_logits.shape[2]
    cells = np.array(list(best.values()))
    pos = position.flatten()[torch.from_numpy(cells)].numpy()
    pixels = np.stack([(cells % cols) * CELL + pos % CELL, (cells // cols) * CELL + pos // CELL], axis=1)
    return np.array(list(best), np.int64), pixels.astype(np.float32), score[cells].numpy().astype(np.float32)
