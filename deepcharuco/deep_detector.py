"""`Detector`: ChArUcoNet (+ RefineNet / cornerSubPix) behind the same interface as `OpenCVDetector`.

    image -> ChArUcoNet -> per-cell point and ID softmax -> best cell per ID (score >= threshold)
          -> board-geometry check (`board_check`): the confident cells' likeliest IDs must fit one
             homography of the board's plane; every corner it predicts takes the cell found there
          -> integer corner pixels -> refine: RefineNet on 24x24 patches (batched), cornerSubPix, or none
          -> Detection
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from deepcharuco.board import BoardSpec
from deepcharuco.board_check import GEOMETRY_MODES, MIN_CONSENSUS, assign_ids, fit_board_homography, id_hypotheses
from deepcharuco.detection import Detection, no_corners
from deepcharuco.errors import DeepCharucoError
from deepcharuco.image import to_gray_u8
from deepcharuco.models.cells import CellCandidates, best_per_id, cell_candidates
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
        geometry: what the board-geometry check does with the network's corners (see `board_check`):
            "repair" (default): the confident cells' two likeliest IDs are fitted to one view of the board
            (RANSAC homography, 6 or more agreeing); the corners that view predicts take the confident cells
            found there (wrong IDs dropped, IDs the ID head was unsure of recovered);
            "filter": keep only the corners that fit the view; "none": the paper's decoding as it is.
            With "repair" or "filter", 6 or more corners that fit no view are all dropped (no answer
            rather than a wrong pose); fewer than 6 cannot be checked and are returned as found, and
            `estimate_pose` gives no pose for them.
    """

    def __init__(self, board: BoardSpec | None = None, weights: str | Path | None = None, refine: str = "refinenet",
                 device: str = "cpu", refine_weights: str | Path | None = None, threshold: float | None = None,
                 soft_radius: int = 2, geometry: str = "repair"):
        if refine not in REFINE_MODES:
            raise ValueError(f"refine must be one of {REFINE_MODES}, got {refine!r}")
        if geometry not in GEOMETRY_MODES:
            raise ValueError(f"geometry must be one of {GEOMETRY_MODES}, got {geometry!r}")
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
        self.geometry = geometry
        self._board_xy = self.board.corner_points()[:, :2]
        self.refinenet = None
        if refine == "refinenet":
            self.refinenet, _ = load_refinenet(refine_weights or weights)
            self.refinenet.to(self.device)

    def __repr__(self) -> str:
        return (f"Detector(board={self.board!r}, refine={self.refine!r}, geometry={self.geometry!r}, "
                f"device={str(self.device)!r})")

    @torch.inference_mode()
    def detect(self, image: np.ndarray) -> Detection:
        """Find the board's corners in a uint8 grayscale (or BGR) image of any size."""
        gray = to_gray_u8(image)
        height, width = gray.shape
        # The network sees whole 8x8 cells: pad right and bottom by replicating the border.
        padded = cv2.copyMakeBorder(gray, 0, -height % CELL, 0, -width % CELL, cv2.BORDER_REPLICATE)
        tensor = torch.from_numpy(padded).to(self.device, torch.float32).div_(255.0)[None, None]
        point_logits, id_logits = self.charuconet(tensor)
        ids, pixels, scores = self.decode(point_logits[0].cpu(), id_logits[0].cpu(), (width, height))
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

    def decode(self, point_logits: torch.Tensor, id_logits: torch.Tensor, image_size: tuple[int, int]
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One image's ChArUcoNet logits (65, Hc, Wc), (N+1, Hc, Wc) -> integer corner pixels before refinement:
        (ids (M,), pixels (M, 2) float32, scores (M,)), decoded at ``self.threshold`` with ``self.geometry``.
        ``image_size``: (width, height) of the image before padding."""
        width, height = image_size
        # A score is at most its cell's confidence: cells less confident than the threshold never count.
        candidates = cell_candidates(point_logits, id_logits, self.threshold)
        inside = (candidates.pixels[:, 0] < width) & (candidates.pixels[:, 1] < height)
        candidates = CellCandidates(candidates.pixels[inside], candidates.confidence[inside], candidates.id_prob[inside])
        ids, pixels, scores = best_per_id(candidates, self.threshold)
        view = None
        if self.geometry == "filter":
            view = fit_board_homography(self._board_xy[ids], pixels)
            if view is not None:
                ids, pixels, scores = ids[view.inliers], pixels[view.inliers], scores[view.inliers]
        elif self.geometry == "repair":
            proposed_ids, proposed_pixels = id_hypotheses(candidates)
            view = fit_board_homography(self._board_xy[proposed_ids], proposed_pixels)
            if view is not None:
                ids, pixels, scores = assign_ids(view, self._board_xy, candidates, (width, height))
        if self.geometry != "none" and view is None and len(ids) >= MIN_CONSENSUS:
            return no_corners()  # enough corners to check, and they fit no view
        return ids, pixels, scores

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
        """`deepcharuco.estimate_pose` for this detector's board.

        With the board-geometry check on (``geometry`` "repair" or "filter") a pose needs a RANSAC
        consensus of at least 6 corners (``min_inliers``): 4 fit some view of the board whatever their
        IDs, so a pose from a few corners may be confidently wrong; the corners are still reported."""
        if self.geometry != "none":
            kwargs.setdefault("min_inliers", MIN_CONSENSUS)
        return estimate_pose(detection, K, dist, board=self.board, **kwargs)
