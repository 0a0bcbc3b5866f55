"""Train the learned marker reader on synthetic cells: ``python -m train.bit_reader --out runs/bit_reader``.

No renderer: each sample is a 5x5-square piece of a ChArUco board drawn in the cell's own frame
(the marker square in the middle, black squares beside it, random markers of the same family
in the diagonal squares, sometimes the board's paper edge on one side), printed normally or
inverted, warped into a small image by a random homography (7-36 px per square), then
photographed badly: defocus, linear motion blur (the paper's horizontal box of up to 12 px, or
any direction), illumination gradients, low light, Poisson + Gaussian sensor noise, rounding to
uint8 (a dark frame keeps 1-3 grey levels), the paper's darkness 0.6^k applied to the uint8
frame, JPEG. An inverted print is negated about the frame's brightest level, as the runtime's
`print_face.canonical_view` does. The square is then rectified through the runtime's own path:
the four corners of a *cell* (the marker square or one of its edge neighbours, as `placement`
reads a cell's neighbours through the cell's homography) are perturbed as the point head's
corners would be, rounded to pixels half the time, and `marker_reader.rectify_squares` samples
the patch. Labels: the marker's inner bits in the cell frame (True = white).

Every random choice comes from ``numpy.random.default_rng([seed, step])``: a run is
determined by its seed and resumes from its checkpoint (``--out``/last.pt) to the same result.
Loss: per-bit binary cross-entropy (its logits are log-likelihood ratios, which `marker_reader`
sums over a candidate marker's bits).

    python -m train.bit_reader --out runs/bit_reader --steps 3000        # ~15 min on 2 loaded cores
    python -m train.bit_reader --out runs/bit_reader --export deepcharuco/weights/bit_reader.pt
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from deepcharuco.detection.markers.marker_reader import MAX_BIT_LOGIT, rectify_squares
from deepcharuco.networks.bit_reader import SIZES, BitReader, BitReaderConfig, normalise_patches, save_bit_reader

# Families per inner size: the _1000 dictionaries hold the _50/_100/_250 ones as prefixes.
FAMILIES: dict[int, tuple[str, ...]] = {
    4: ("DICT_4X4_1000",), 5: ("DICT_5X5_1000",), 6: ("DICT_6X6_1000", "DICT_APRILTAG_36h11"), 7: ("DICT_7X7_1000",),
}
TEXTURE_SQUARE = 48  # texture pixels per square: >= the supersampled image's, so warping only minifies
SUPERSAMPLE = 2
NEIGHBOURHOOD = 5  # squares per side drawn around the marker square (its blur context)
CELL_OFFSETS = np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]])
OBJECTIVES = ("bits", "match")
MATCH_NEGATIVES = 63  # other markers of the family per read ("match"), each in 4 turns
MATCH_SCALE = 10.0  # cosine -> softmax logit: a cosine margin of 0.3 is a factor e^3 in probability


@dataclass(frozen=True)
class Degradation:
    """The ranges the samples are drawn from (the paper's protocols reach blur k = 10 and darkness k = 10)."""

    # Pixels per marker bit, log-uniform: below 1 no reader can tell bits apart; the unseen 11x8 board at
    # 320x240 has ~2, its squares 11-25 px. The square follows from the bit, the marker size and the ratio.
    bit_px: tuple[float, float] = (1.0, 5.0)
    max_motion_px: float = 12.0
    max_defocus_sigma: float = 1.5
    max_darkness_k: float = 10.5
    max_read_noise: float = 3.0
    max_shot_gain: float = 0.5  # grey levels per photo-electron
    # The point head's corners are whole pixels (an 8x8 cell's argmax), about half a pixel off.
    corner_noise_px: tuple[float, float] = (0.1, 0.6)
    corner_noise_fraction: float = 0.02  # ... plus this fraction of the square side (coarse-level corners)


@cache
def family_bits(dictionary: str) -> np.ndarray:
    """(K, n + 2, n + 2) bool: every marker of ``dictionary`` with its border, True = white, row = y."""
    cv_dict = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    size = cv_dict.markerSize + 2
    count = cv_dict.bytesList.shape[0]
    return np.stack([cv2.aruco.generateImageMarker(cv_dict, i, size, borderBits=1) > 127 for i in range(count)])


def _neighbourhood_texture(rng: np.random.Generator, size: int, ratio: float) -> tuple[np.ndarray, np.ndarray, float]:
    """A board piece in the middle square's frame -> (texture (T, T) float32, 1 = paper, 0 = ink; the middle
    marker's inner bits (n, n) bool; the drawn marker/square ratio). Square (i, j) spans texture pixels
    [48 i, 48 (i + 1)) (``TEXTURE_SQUARE``), the marker square is (2, 2)."""
    dictionary = FAMILIES[size][rng.integers(len(FAMILIES[size]))]
    markers = family_bits(dictionary)
    side = TEXTURE_SQUARE
    cells = size + 2
    per_bit = max(1, int(round(ratio * side / cells)))
    if (side - per_bit * cells) % 2:  # keep the marker centred on whole texture pixels
        per_bit = per_bit + 1 if per_bit * cells < ratio * side else per_bit - 1
    marker_px = per_bit * cells
    start = (side - marker_px) // 2
    texture = np.ones((NEIGHBOURHOOD * side, NEIGHBOURHOOD * side), np.float32)
    middle = NEIGHBOURHOOD // 2
    target = None
    for row in range(NEIGHBOURHOOD):
        for col in range(NEIGHBOURHOOD):
            y0, x0 = row * side, col * side
            if (row + col) % 2:  # the black squares beside every marker square
                texture[y0:y0 + side, x0:x0 + side] = 0.0
                continue
            marker = np.rot90(markers[rng.integers(len(markers))], k=int(rng.integers(4)))
            block = np.repeat(np.repeat(marker.astype(np.float32), per_bit, axis=0), per_bit, axis=1)
            texture[y0 + start:y0 + start + marker_px, x0 + start:x0 + start + marker_px] = block
            if row == middle and col == middle:
                target = marker[1:-1, 1:-1].copy()
    if rng.random() < 0.35:  # the board's edge: paper beyond one side, one or two squares out
        depth = 1 if rng.random() < 0.7 else 2
        edge = slice(0, depth * side) if rng.random() < 0.5 else slice((NEIGHBOURHOOD - depth) * side, None)
        if rng.random() < 0.5:
            texture[edge, :] = 1.0
        else:
            texture[:, edge] = 1.0
    return texture, target, marker_px / side


def _square_corners(rng: np.random.Generator, side_px: float, centre: float) -> np.ndarray:
    """(4, 2) image corners of the marker square (unit corners (0,0), (1,0), (1,1), (0,1)): any rotation,
    foreshortened up to 2:1 and skewed, with some perspective."""
    unit = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float64) - 0.5
    angle = rng.uniform(0, 2 * math.pi)
    squash = np.diag([1.0, rng.uniform(0.55, 1.0)])
    turn = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    tilt = rng.uniform(0, 2 * math.pi)
    axis = np.array([[math.cos(tilt), -math.sin(tilt)], [math.sin(tilt), math.cos(tilt)]])
    linear = side_px * turn @ axis @ squash @ axis.T
    linear = linear @ np.array([[1.0, rng.normal(0, 0.12)], [0.0, 1.0]])
    corners = unit @ linear.T + rng.normal(0, 0.05 * side_px, (4, 2))  # perspective: each corner a little off
    return corners + centre


def _motion_kernel(rng: np.random.Generator, length: float) -> np.ndarray:
    """A normalised linear motion kernel of ``length`` px: the paper's horizontal box half the time, else a
    line at any angle (drawn anti-aliased)."""
    if rng.random() < 0.5:
        k = max(1, int(round(length)))
        return np.ones((1, k), np.float32) / k
    size = int(math.ceil(length)) | 1
    kernel = np.zeros((size * 4, size * 4), np.float32)
    angle = rng.uniform(0, math.pi)
    half = length * 2
    centre = size * 2
    p0 = (int(round((centre - half * math.cos(angle)) * 16)), int(round((centre - half * math.sin(angle)) * 16)))
    p1 = (int(round((centre + half * math.cos(angle)) * 16)), int(round((centre + half * math.sin(angle)) * 16)))
    cv2.line(kernel, p0, p1, 1.0, 2, cv2.LINE_AA, shift=4)
    kernel = cv2.resize(kernel, (size, size), interpolation=cv2.INTER_AREA)
    return kernel / max(kernel.sum(), 1e-9)


def render_cell(rng: np.random.Generator, size: int, degradation: Degradation = Degradation()
                ) -> tuple[np.ndarray, np.ndarray]:
    """One training sample: (rectified patch (P, P) float32 grey levels, inner bits (n, n) bool, True = white)."""
    texture, target, ratio = _neighbourhood_texture(rng, size, rng.uniform(0.5, 0.85))
    inverted = rng.random() < 0.25
    if inverted:  # white squares and markers printed on black paper
        texture = 1.0 - texture
    low, high = degradation.bit_px
    side_px = max(6.0, math.exp(rng.uniform(math.log(low), math.log(high))) * (size + 2) / ratio)
    # The patch spans at most 1.45 squares (4x4 markers at ratio 0.85 with their margin): 2.6 squares hold it
    # turned and foreshortened, plus what a blur smears in.
    canvas = int(math.ceil(side_px * 2.6 + 2 * degradation.max_motion_px)) + 4
    corners = _square_corners(rng, side_px, canvas / 2)
    unit = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    square_to_image = cv2.getPerspectiveTransform(unit, corners.astype(np.float32)).astype(np.float64)
    middle = NEIGHBOURHOOD // 2
    texture_to_square = np.array([[1 / TEXTURE_SQUARE, 0, 0.5 / TEXTURE_SQUARE - middle],
                                  [0, 1 / TEXTURE_SQUARE, 0.5 / TEXTURE_SQUARE - middle], [0, 0, 1]])
    half = (SUPERSAMPLE - 1) / 2
    to_fine = np.array([[SUPERSAMPLE, 0, half], [0, SUPERSAMPLE, half], [0, 0, 1.0]])
    background = rng.uniform(0, 1)
    fine = cv2.warpPerspective(texture, to_fine @ square_to_image @ texture_to_square,
                               (canvas * SUPERSAMPLE, canvas * SUPERSAMPLE), flags=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=float(background))
    image = cv2.resize(fine, (canvas, canvas), interpolation=cv2.INTER_AREA)
    # Light: paper level, ink as a fraction of it (matte ink reflects 5-50 %), a gradient across the cell.
    paper = rng.uniform(60, 250)
    ink = paper * rng.uniform(0.04, 0.4)
    yy, xx = np.mgrid[0:canvas, 0:canvas].astype(np.float32) / canvas - 0.5
    shade = 1 + rng.normal(0, 0.15) * xx + rng.normal(0, 0.15) * yy
    image = (ink + (paper - ink) * image) * np.clip(shade, 0.3, 2.0)
    if rng.random() < 0.4:
        image = cv2.GaussianBlur(image, (0, 0), rng.uniform(0.3, degradation.max_defocus_sigma))
    motion = rng.uniform(1, degradation.max_motion_px) if rng.random() < 0.5 else 0.0
    motion_first = rng.random() < 0.5  # real motion smears light before the sensor; the paper's blur the frame
    if motion and motion_first:
        image = cv2.filter2D(image, -1, _motion_kernel(rng, motion), borderType=cv2.BORDER_REPLICATE)
    # Darkness: none, low light at capture (few photons, the same read noise), or the paper's protocol on the
    # uint8 frame; rarely on top of motion (the protocols test each alone; both at once leave little to learn).
    darkness = rng.choice(3, p=[0.7, 0.15, 0.15] if motion else [0.3, 0.3, 0.4])
    if darkness == 1:
        image = image * 0.6 ** rng.uniform(0, degradation.max_darkness_k)
    gain = rng.uniform(0.0, degradation.max_shot_gain)  # shot noise variance = gain * signal
    read_noise = rng.uniform(0, degradation.max_read_noise)
    image = image + rng.standard_normal(image.shape, np.float32) * np.sqrt(gain * np.maximum(image, 0) + read_noise ** 2)
    image = np.clip(np.round(image), 0, 255).astype(np.uint8)
    if motion and not motion_first:
        image = cv2.filter2D(image, -1, _motion_kernel(rng, motion), borderType=cv2.BORDER_REPLICATE)
    if darkness == 2:  # x 0.6^k, rounded, as evaluate.paper.protocols.darken
        image = np.round(image * 0.6 ** rng.uniform(0, degradation.max_darkness_k)).astype(np.uint8)
    if rng.random() < 0.2:
        ok, encoded = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(40, 96))])
        image = cv2.imdecode(encoded, cv2.IMREAD_GRAYSCALE)
    if inverted:
        image = int(image.max()) - image  # print_face.canonical_view
    # The runtime's path: a cell's corners as the point head finds them, the square through that cell.
    offset = CELL_OFFSETS[0] if rng.random() < 0.4 else CELL_OFFSETS[rng.integers(1, len(CELL_OFFSETS))]
    cell = (unit + offset).astype(np.float64)
    cell_corners = cv2.perspectiveTransform(cell[None], square_to_image)[0]
    low_noise, high_noise = degradation.corner_noise_px
    sigma = rng.uniform(low_noise, high_noise) + rng.uniform(0, degradation.corner_noise_fraction) * side_px
    cell_corners = cell_corners + rng.normal(0, sigma, cell_corners.shape)
    if rng.random() < 0.5:
        cell_corners = np.round(cell_corners)
    cell_to_image = cv2.getPerspectiveTransform(unit, cell_corners.astype(np.float32)).astype(np.float64)
    # The marker square's point s is the cell's point s - offset (placement reads a neighbour the same way).
    shift = np.array([[1, 0, -offset[0]], [0, 1, -offset[1]], [0, 0, 1]], np.float64)
    patch = rectify_squares(image, (cell_to_image @ shift)[None], size, ratio)[0]
    return patch, target


def make_batch(seed: int, step: int, batch: int, degradation: Degradation = Degradation()
               ) -> tuple[int, np.ndarray, np.ndarray]:
    """The batch of ``step``: (inner size n, normalised patches (B, P, P) float32, bits (B, n, n) float32)."""
    rng = np.random.default_rng([seed, step])
    size = int(SIZES[rng.integers(len(SIZES))])
    samples = [render_cell(rng, size, degradation) for _ in range(batch)]
    patches = normalise_patches(np.stack([p for p, _ in samples]))
    return size, patches, np.stack([t for _, t in samples]).astype(np.float32)


def candidate_signs(rng: np.random.Generator, size: int, bits: np.ndarray, negatives: int = MATCH_NEGATIVES
                    ) -> np.ndarray:
    """(B, n, n) true bits -> (B, 4 (1 + negatives), n * n) float32 signs (+1 white) of the candidates a read is
    matched against: the true marker in its 4 quarter turns (index 0: as read), then ``negatives`` other
    markers of the family in 4 turns each (as `marker_reader` matches a board's markers in 4 turns)."""
    family = family_bits(FAMILIES[size][0])[:, 1:-1, 1:-1]
    others = family[rng.integers(len(family), size=(len(bits), negatives))]  # (B, K, n, n)
    markers = np.concatenate([bits[:, None] > 0.5, others], axis=1)
    turned = np.stack([np.rot90(markers, k, axes=(2, 3)) for k in range(4)], axis=2)  # (B, K + 1, 4, n, n)
    return (turned.reshape(len(bits), -1, size * size).astype(np.float32) * 2 - 1)


def match_scores(logits: torch.Tensor, signs: torch.Tensor) -> torch.Tensor:
    """(B, n, n) bit logits, (B, C, n * n) candidate signs -> (B, C) the runtime's score (`marker_reader.correlate`,
    reader "learned"): the cosine of tanh(logit / MAX_BIT_LOGIT) with each candidate's signs."""
    bounded = torch.tanh(logits.flatten(1) / MAX_BIT_LOGIT)
    norm = bounded.norm(dim=1, keepdim=True).clamp_min(1e-6) * math.sqrt(signs.shape[2])
    return torch.einsum("bcn,bn->bc", signs, bounded) / norm


def _validation_set(seed: int, batches: int, batch: int) -> list[tuple[int, torch.Tensor, torch.Tensor, torch.Tensor]]:
    """Fixed batches (seed + 1: never a training batch's seed) -> [(n, patches (B, 1, P, P), bits (B, n, n),
    candidate signs (B, C, n * n))]."""
    out = []
    for step in range(batches):
        size, patches, bits = make_batch(seed + 1, step, batch)
        signs = candidate_signs(np.random.default_rng([seed + 1, step, 1]), size, bits)
        out.append((size, torch.from_numpy(patches)[:, None], torch.from_numpy(bits), torch.from_numpy(signs)))
    return out


@torch.no_grad()
def evaluate(model: BitReader, validation: list) -> dict[str, float]:
    """Mean per-bit BCE, bit accuracy, whole-marker accuracy (every bit right) and match accuracy (the true
    marker in its turn scores best among 64 markers x 4 turns, `match_scores`) on the validation batches."""
    model.eval()
    loss, bit_ok, marker_ok, match_ok, bits_total, markers_total = 0.0, 0.0, 0.0, 0.0, 0, 0
    for size, patches, bits, signs in validation:
        logits = model(patches, size)
        match_ok += float((match_scores(logits, signs).argmax(dim=1) == 0).sum())
        loss += float(F.binary_cross_entropy_with_logits(logits, bits, reduction="sum"))
        right = (logits > 0) == (bits > 0.5)
        bit_ok += float(right.sum())
        marker_ok += float(right.flatten(1).all(dim=1).sum())
        bits_total += bits.numel()
        markers_total += len(bits)
    model.train()
    return {"val_loss": loss / bits_total, "val_bit_acc": bit_ok / bits_total, "val_marker_acc": marker_ok / markers_total,
            "val_match_acc": match_ok / markers_total}


def train(out: Path, steps: int, batch: int = 128, seed: int = 0, lr: float = 3e-3, config: BitReaderConfig = BitReaderConfig(),
          validate_every: int = 250, quiet: bool = False, objective: str = "bits", init: Path | None = None) -> dict:
    """Train (or resume from ``out``/last.pt) to ``steps``; -> the last validation metrics.

    ``objective``: "bits" (per-bit BCE: logits are log-likelihood ratios) or "match" (softmax over the
    runtime's scores of the true marker against 63 others in 4 turns each, `match_scores`: under a blur the
    bits' marginals lose what the bits' joint says, e.g. a row's sum; this trains the score that is used).
    ``init``: a run folder whose last.pt starts the model (e.g. "match" after "bits").
    Writes ``out``/last.pt (model, optimiser, step, seed) every ``validate_every`` steps and at the end, and
    ``out``/log.csv (step, loss, validation metrics)."""
    if objective not in OBJECTIVES:
        raise ValueError(f"objective must be one of {OBJECTIVES}, got {objective!r}")
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(seed)
    model = BitReader(config)
    if init is not None:
        model.load_state_dict(torch.load(Path(init) / "last.pt", map_location="cpu", weights_only=False)["model"])
    optimiser = torch.optim.Adam(model.parameters(), lr=lr)
    # Cosine decay to 5 % over the run: the plain rate plateaus on the noisiest samples.
    schedule = torch.optim.lr_scheduler.LambdaLR(
        optimiser, lambda s: 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(s, steps) / max(steps, 1))))
    start = 0
    checkpoint = out / "last.pt"
    if checkpoint.is_file():
        state = torch.load(checkpoint, map_location="cpu", weights_only=False)
        if state["seed"] != seed or state["config"] != config.to_dict() or state["steps"] != steps \
                or state.get("objective", "bits") != objective:
            raise SystemExit(f"error: {checkpoint} was trained with seed {state['seed']}, {state['steps']} steps, "
                             f"objective {state.get('objective', 'bits')}, config {state['config']}: resume with "
                             f"the same, or use another --out")
        model.load_state_dict(state["model"])
        optimiser.load_state_dict(state["optimiser"])
        schedule.load_state_dict(state["schedule"])
        start = int(state["step"])
    validation = _validation_set(seed, batches=8, batch=128)
    log = out / "log.csv"
    if start == 0 or not log.is_file():
        log.write_text("step,loss,val_loss,val_bit_acc,val_marker_acc,val_match_acc,seconds\n")
    metrics = evaluate(model, validation) if start >= steps else {}
    running, began = [], time.time()
    with tqdm(total=steps, initial=start, unit="step", disable=quiet, desc="bit reader") as bar:
        for step in range(start, steps):
            size, patches, bits = make_batch(seed, step, batch)
            logits = model(torch.from_numpy(patches)[:, None], size)
            if objective == "bits":
                loss = F.binary_cross_entropy_with_logits(logits, torch.from_numpy(bits))
            else:
                signs = torch.from_numpy(candidate_signs(np.random.default_rng([seed, step, 1]), size, bits))
                scores = MATCH_SCALE * match_scores(logits, signs)
                loss = F.cross_entropy(scores, torch.zeros(len(scores), dtype=torch.long))
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            schedule.step()
            running.append(loss.item())
            bar.update(1)
            bar.set_postfix(loss=f"{np.mean(running[-50:]):.3f}")
            done = step + 1
            if done % validate_every == 0 or done == steps:
                metrics = evaluate(model, validation)
                with log.open("a") as handle:
                    handle.write(f"{done},{np.mean(running[-validate_every:]):.5f},{metrics['val_loss']:.5f},"
                                 f"{metrics['val_bit_acc']:.5f},{metrics['val_marker_acc']:.5f},"
                                 f"{metrics['val_match_acc']:.5f},{time.time() - began:.1f}\n")
                temporary = out / "last.pt.tmp"
                torch.save({"model": model.state_dict(), "optimiser": optimiser.state_dict(),
                            "schedule": schedule.state_dict(), "step": done, "seed": seed, "steps": steps,
                            "config": config.to_dict(), "metrics": metrics, "objective": objective}, temporary)
                temporary.replace(checkpoint)
                bar.write(f"step {done}: " + ", ".join(f"{k} {v:.4f}" for k, v in metrics.items()))
    return metrics


def export(out: Path, weights: Path) -> Path:
    """Write the run's model (``out``/last.pt) as shipped weights (float16, `save_bit_reader`)."""
    state = torch.load(out / "last.pt", map_location="cpu", weights_only=False)
    model = BitReader(BitReaderConfig.from_dict(state["config"]))
    model.load_state_dict(state["model"])
    return save_bit_reader(model, weights, {"seed": state["seed"], "steps": state["step"], "metrics": state["metrics"],
                                            "command": f"python -m train.bit_reader --out {out} --steps {state['steps']} "
                                                       f"--seed {state['seed']}"})


# Validation boards for choosing the reader: none of them is an evaluate.paper.unseen_boards board (those measure, they
# do not tune); every family and print the runtime meets.
VALIDATION_BOARDS = (
    dict(squares_x=9, squares_y=6, square_length=0.03, marker_length=0.021, dictionary="DICT_5X5_250"),
    dict(squares_x=8, squares_y=6, square_length=0.03, marker_length=0.0225, dictionary="DICT_6X6_1000"),
    dict(squares_x=5, squares_y=4, square_length=0.04, marker_length=0.03, dictionary="DICT_4X4_100", inverted=True),
    dict(squares_x=6, squares_y=6, square_length=0.04, marker_length=0.03, dictionary="DICT_APRILTAG_36h11"),
    dict(squares_x=6, squares_y=5, square_length=0.04, marker_length=0.032, dictionary="DICT_7X7_100"),
)
VALIDATION_CONDITIONS = (("k0", "blur", 0), ("blur10", "blur", 10), ("dark9", "darkness", 9))


def validation_views(seed: int, per_board: int) -> list[tuple[object, np.ndarray, np.ndarray]]:
    """Exact 320x240 views (`synthetic.render_board_view`) of `VALIDATION_BOARDS` as a printed board looks in
    the renders (paper 150-230, ink 25-75 grey levels, a light gradient, sensor noise), squares ~11-30 px,
    -> [(board, image (240, 320) uint8, true corners (C, 2))]."""
    from deepcharuco import BoardSpec, Camera, project_corners
    from deepcharuco.boards.synthetic import look_at_pose, render_board_view

    rng = np.random.default_rng([seed, 7])
    camera = Camera.from_fov(320, 240, hfov_deg=60.0)
    views = []
    for spec in VALIDATION_BOARDS:
        board = BoardSpec(**spec)
        for _ in range(per_board):
            fill = rng.uniform(0.55, 0.95)
            distance = camera.K[0, 0] * max(board.size_m) / (fill * 240)
            rvec, tvec = look_at_pose(board, distance, tilt_x_deg=rng.uniform(-35, 35), tilt_y_deg=rng.uniform(-35, 35),
                                      roll_deg=rng.uniform(0, 360), offset=tuple(rng.uniform(-0.1, 0.1, 2) * distance))
            image = render_board_view(board, camera.K, rvec, tvec, (320, 240), background=int(rng.integers(40, 200)))
            white = 1.0 - image.astype(np.float32) / 255 if board.inverted else image.astype(np.float32) / 255
            paper, ink = rng.uniform(150, 230), rng.uniform(25, 75)
            lit = ink + (paper - ink) * white
            lit = 255 - lit if board.inverted else lit  # keep the print's polarity (inverted prints stay negative)
            yy, xx = np.mgrid[0:240, 0:320].astype(np.float32)
            lit = lit * (1 + rng.normal(0, 0.2) * (xx / 320 - 0.5) + rng.normal(0, 0.2) * (yy / 240 - 0.5))
            lit = lit + rng.normal(0, 2.0, lit.shape)
            views.append((board, np.clip(np.rint(lit), 0, 255).astype(np.uint8),
                          project_corners(board, rvec, tvec, camera.K)))
    return views


def compare_readers(views: list, readers: tuple[str, ...] = ("sampled", "learned"), quiet: bool = False
                    ) -> dict[str, dict[str, float]]:
    """The deep detector's corner accuracy (ID right, < 3 px, over the corners inside the image) on ``views``
    under `VALIDATION_CONDITIONS`, with each marker reader -> {reader: {condition: mean accuracy}}."""
    from deepcharuco import Detector
    from deepcharuco.detection.markers import marker_reader
    from deepcharuco.detection.metrics import match_corners
    from evaluate.paper.protocols import darken, motion_blur

    detectors: dict = {}
    result = {reader: {name: [] for name, _, _ in VALIDATION_CONDITIONS} for reader in readers}
    default = marker_reader.DEFAULT_READER
    total = len(readers) * len(views) * len(VALIDATION_CONDITIONS)
    try:
        with tqdm(total=total, desc="validation views", unit="image", disable=quiet) as bar:
            for reader in readers:
                marker_reader.DEFAULT_READER = reader  # Detector has no reader argument: the module's default
                for board, image, truth in views:
                    detector = detectors.setdefault(board, Detector(board=board))
                    for name, effect, k in VALIDATION_CONDITIONS:
                        degraded, shift = motion_blur(image, k) if effect == "blur" else (darken(image, k), 0.0)
                        moved = truth + np.array([shift, 0.0])
                        inside = (moved[:, 0] >= 0) & (moved[:, 0] <= 319) & (moved[:, 1] >= 0) & (moved[:, 1] <= 239)
                        match = match_corners(detector.detect(degraded), moved, inside)
                        result[reader][name].append(match.num_correct / max(int(inside.sum()), 1))
                        bar.update(1)
    finally:
        marker_reader.DEFAULT_READER = default
    return {reader: {name: float(np.mean(values)) for name, values in rows.items()} for reader, rows in result.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m train.bit_reader", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--out", required=True, help="run folder (last.pt, log.csv); an existing run resumes")
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--batch", type=int, default=128)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--lr", type=float, default=3e-3)
    parser.add_argument("--objective", choices=OBJECTIVES, default="bits", help="per-bit BCE, or the runtime's "
                        "marker score against other markers (see train())")
    parser.add_argument("--init", default=None, help="start from this run folder's last.pt (e.g. --objective "
                        "match after a bits run)")
    parser.add_argument("--width", type=int, default=BitReaderConfig.width, help="channels per bit cell")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (the machine is shared)")
    parser.add_argument("--export", default=None, help="after training, write the weights here (e.g. "
                        "deepcharuco/weights/bit_reader.pt)")
    parser.add_argument("--compare", type=int, default=0, metavar="N",
                        help="instead of training: the detector with each reader on N validation views per board "
                             "(the shipped reader weights)")
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    if args.steps < 1 or args.batch < 1:
        parser.error("--steps and --batch must be >= 1")
    torch.set_num_threads(args.threads)
    if args.compare:
        scores = compare_readers(validation_views(args.seed, args.compare), quiet=args.quiet)
        for reader, row in scores.items():
            print(f"{reader}: " + ", ".join(f"{name} {value:.3f}" for name, value in row.items()))
        return 0
    out = Path(args.out)
    metrics = train(out, args.steps, args.batch, args.seed, args.lr, BitReaderConfig(width=args.width), quiet=args.quiet,
                    objective=args.objective, init=Path(args.init) if args.init else None)
    print(", ".join(f"{k} {v:.4f}" for k, v in metrics.items()))
    if args.export:
        print(f"wrote {export(out, Path(args.export))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
