"""`Detector`: ChArUcoNet (+ RefineNet / cornerSubPix) behind the same interface as `OpenCVDetector`.

    image -> ChArUcoNet -> per-cell point and ID softmax -> best cell per ID (score >= threshold)
          -> integer corner pixels -> refine: RefineNet on 24x24 patches (batched), cornerSubPix, or none
          -> Detection
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from deepcharuco.board import BoardSpec
from deepcharuco.detection import Detection
from deepcharuco.errors import DeepCharucoError
from deepcharuco.image import to_gray_u8
from deepcharuco.models.cells import decode_cells
from deepcharuco.models.charuconet import CELL
from deepcharuco.models.checkpoint import load_charuconet, load_refinenet
from deepcharuco.models.refinenet import PATCH, decode_offsets
from deepcharuco.pose import Pose, estimate_pose

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
DEFAULT_WEIGHTS = WEIGHTS_DIR / "detector.pt"
REFINE_MODES = ("refinenet", "subpix", "none")
DEFAULT_THRESHOLD = 0.3
PATCH_ORIGIN = 12  # a candidate pixel sits at patch pixel 12, inside the central 8x8 (8..15)


class Detector:
    """The deep ChArUco detector.

    Args:
        board: the board; must be the one the weights were trained for (default: the weights' board).
        weights: a ChArUcoNet checkpoint or a bundle with both networks (default: the shipped weights).
        refine: "refinenet" (the paper's best), "subpix" (OpenCV cornerSubPix) or "none" (cell pixels).
        device: "cpu", "cuda", "mps" ...
        refine_weights: RefineNet checkpoint when ``weights`` holds only ChArUcoNet.
        threshold: the smallest score (point confidence x ID probability) a corner is reported at
            (default: the operating point stored with the weights, chosen on validation frames; else 0.3).
        soft_radius: RefineNet soft-argmax window (cells of 1/8 px) around the argmax; 0 = argmax only.
    """

    def __init__(self, board: BoardSpec | None = None, weights: str | Path | None = None, refine: str = "refinenet",
                 device: str = "cpu", refine_weights: str | Path | None = None, threshold: float | None = None,
                 soft_radius: int = 2):
        if refine not in REFINE_MODES:
            raise ValueError(f"refine must be one of {REFINE_MODES}, got {refine!r}")
        if weights is None:
            weights = DEFAULT_WEIGHTS
            if not weights.is_file():
                raise DeepCharucoError(
                    f"no shipped weights in this version ({weights} is missing): train them with python -m "
                    f"train.charuconet and python -m train.refinenet, then pass weights=..., refine_weights=...")
        self.device = torch.device(device)
        self.charuconet, self.board, self.checkpoint = load_charuconet(weights, board)
        self.charuconet.to(self.device)
        self.refine = refine
        self.threshold = float(threshold if threshold is not None else self.checkpoint.get("threshold", DEFAULT_THRESHOLD))
        self.soft_radius = int(soft_radius)
        self.refinenet = None
        if refine == "refinenet":
            self.refinenet, _ = load_refinenet(refine_weights or weights)
            self.refinenet.to(self.device)

    def __repr__(self) -> str:
        return f"Detector(board={self.board!r}, refine={self.refine!r}, device={str(self.device)!r})"

    @torch.inference_mode()
    def detect(self, image: np.ndarray) -> Detection:
        """Find the board's corners in a uint8 grayscale (or BGR) image of any size."""
        gray = to_gray_u8(image)
        height, width = gray.shape
        # The network sees whole 8x8 cells: pad right and bottom by replicating the border.
        padded = cv2.copyMakeBorder(gray, 0, -height % CELL, 0, -width % CELL, cv2.BORDER_REPLICATE)
        tensor = torch.from_numpy(padded).to(self.device, torch.float32).div_(255.0)[None, None]
        point_logits, id_logits = self.charuconet(tensor)
        ids, pixels, scores = decode_cells(point_logits[0].cpu(), id_logits[0].cpu(), self.threshold)
        inside = (pixels[:, 0] < width) & (pixels[:, 1] < height)
        ids, pixels, scores = ids[inside], pixels[inside], scores[inside]
        if len(ids) == 0:
            return Detection.empty()
        if self.refine == "refinenet":
            corners = self._refinenet(gray, pixels)
        elif self.refine == "subpix":
            criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 0.01)
            corners = cv2.cornerSubPix(gray, pixels.reshape(-1, 1, 2).copy(), (3, 3), (-1, -1), criteria).reshape(-1, 2)
        else:
            corners = pixels
        return Detection(ids=ids, corners=corners, scores=scores)

    def _refinenet(self, gray: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        """Batched RefineNet over 24x24 patches whose pixel 12 is each candidate pixel."""
        border = PATCH
        padded = cv2.copyMakeBorder(gray, border, border, border, border, cv2.BORDER_REPLICATE)
        origins = pixels.astype(np.int64) - PATCH_ORIGIN  # patch top-left in image pixels
        patches = np.stack([padded[y + border:y + border + PATCH, x + border:x + border + PATCH] for x, y in origins])
        tensor = torch.from_numpy(patches).to(self.device, torch.float32).div_(255.0)[:, None]
        offsets = decode_offsets(self.refinenet(tensor), self.soft_radius).cpu().numpy()
        return (origins + offsets).astype(np.float32)

    def estimate_pose(self, detection: Detection, K: np.ndarray, dist: np.ndarray | None = None, **kwargs) -> Pose | None:
        """`deepcharuco.estimate_pose` for this detector's board."""
        return estimate_pose(detection, K, dist, board=self.board, **kwargs)
