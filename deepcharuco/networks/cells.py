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

from dataclasses import dataclass

import numpy as np

from deepcharuco.core.detection import no_corners

CELL = 8  # pixels per ChArUcoNet output cell side: three 2x poolings


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


@dataclass(frozen=True)
class CellCandidates:
    """Cells where ChArUcoNet sees a corner, before IDs are settled.

    Attributes:
        pixels: (M, 2) float32 x, y of each cell's most likely corner pixel.
        confidence: (M,) float32 point confidence, 1 - P(point dustbin).
        id_prob: (M, N) float32 P(ID) over the board's N corners (the ID dustbin left out).
    """

    pixels: np.ndarray
    confidence: np.ndarray
    id_prob: np.ndarray

    def __len__(self) -> int:
        return len(self.confidence)

    def subset(self, keep: np.ndarray) -> "CellCandidates":
        """The cells selected by ``keep`` ((M,) bool mask or indices)."""
        return CellCandidates(self.pixels[keep], self.confidence[keep], self.id_prob[keep])


def as_array(logits) -> np.ndarray:
    """Logits as a float32 numpy array: a numpy array as it is, a PyTorch tensor (any device) copied to the CPU."""
    if hasattr(logits, "detach"):  # a torch.Tensor, without importing torch for the check
        return logits.detach().float().cpu().numpy()
    return np.asarray(logits, np.float32)


def _softmax(logits: np.ndarray, axis: int) -> np.ndarray:
    shifted = np.exp(logits - logits.max(axis=axis, keepdims=True))
    return shifted / shifted.sum(axis=axis, keepdims=True)


def cell_confidence(point_logits: np.ndarray) -> np.ndarray:
    """One image's point logits (65, Hc, Wc) -> (Hc, Wc) float32 probability that each cell holds a corner
    (1 - the dustbin's softmax probability; only the dustbin's is needed)."""
    logits = as_array(point_logits)
    flat = logits.reshape(len(logits), -1)
    top = flat.max(axis=0)
    dustbin = np.exp(flat[-1] - top) / np.exp(flat - top).sum(axis=0)
    return (1.0 - dustbin).astype(np.float32).reshape(logits.shape[1:])


def point_candidates(point_logits: np.ndarray, min_confidence: float, confidence: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One image's point logits (65, Hc, Wc) -> the cells whose point confidence reaches ``min_confidence``:
    (flat cell indices (M,) int64, pixels (M, 2) float32 x, y of each cell's likeliest pixel, confidence (M,) float32).
    ``confidence``: `cell_confidence` of these logits where the caller has it already.

    In numpy: on these small arrays PyTorch's thread pool costs more than the arithmetic, and far more on a
    busy CPU. Only the dustbin's probability is needed (the likeliest pixel is the largest logit)."""
    logits = as_array(point_logits)
    cols = logits.shape[2]
    flat = logits.reshape(len(logits), -1)
    confidence = (cell_confidence(logits) if confidence is None else confidence).ravel()
    cells = np.flatnonzero(confidence >= min_confidence)
    position = flat[:-1, cells].argmax(axis=0)  # 0..63 inside each cell
    pixels = np.stack([(cells % cols) * CELL + position % CELL, (cells // cols) * CELL + position // CELL], axis=1)
    return cells, pixels.astype(np.float32).reshape(-1, 2), confidence[cells]


def cell_candidates(point_logits: np.ndarray, id_logits: np.ndarray | None,
                    min_confidence: float, confidence: np.ndarray | None = None) -> CellCandidates:
    """One image's logits (65, Hc, Wc) and (N+1, Hc, Wc) -> the cells whose point confidence reaches ``min_confidence``.
    Without ``id_logits`` (a board the ID head does not know) ``id_prob`` is (M, 0). ``confidence``: as for
    `point_candidates`."""
    cells, pixels, confidence = point_candidates(point_logits, min_confidence, confidence)
    if id_logits is None:
        return CellCandidates(pixels=pixels, confidence=confidence, id_prob=np.zeros((len(cells), 0), np.float32))
    logits = as_array(id_logits)
    num_corners = logits.shape[0] - 1
    id_prob = _softmax(logits.reshape(len(logits), -1)[:, cells].T, axis=1)  # only the candidate cells
    return CellCandidates(pixels=pixels, confidence=confidence,
                          id_prob=id_prob[:, :-1].astype(np.float32).reshape(-1, num_corners))


def best_per_id(candidates: CellCandidates, threshold: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The paper's decoding: each cell takes its most likely ID, score = confidence x P(ID); for each ID the
    best-scoring cell is kept if its score reaches ``threshold``. -> (ids (M,), pixels (M, 2), scores (M,))."""
    if len(candidates) == 0:
        return no_corners()
    corner_id = candidates.id_prob.argmax(axis=1)
    score = candidates.confidence * candidates.id_prob.max(axis=1)
    order = np.argsort(-score, kind="stable")
    order = order[score[order] >= threshold]
    _, first = np.unique(corner_id[order], return_index=True)  # each ID's best cell, IDs ascending
    keep = order[first]
    keep = keep[np.argsort(-score[keep], kind="stable")]  # strongest first
    return corner_id[keep].astype(np.int64), candidates.pixels[keep], score[keep].astype(np.float32)


def decode_cells(point_logits: np.ndarray, id_logits: np.ndarray, threshold: float = 0.3
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One image's logits (65, Hc, Wc) and (N+1, Hc, Wc) -> (ids (M,), pixels (M, 2) float32 x,y, scores (M,)).

    At most one detection per ID: the best-scoring cell (see the module docstring)."""
    # A score is at most its cell's confidence, so cells below the threshold in confidence never win.
    return best_per_id(cell_candidates(point_logits, id_logits, threshold), threshold)
