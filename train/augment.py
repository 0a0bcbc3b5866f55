"""The paper's augmentation table, with labels moved along with the image.

    effect                      probability
    additive Gaussian noise     0.5
    motion blur                 0.5
    Gaussian blur               0.25
    speckle noise               0.5
    brightness rescale          0.5   (down to near-black: the point of the paper)
    shadow or spotlight         0.5
    homographic transform       1.0 on positives, 0.0 on negatives

The photometric effects run in a random order at random strengths; the homography runs first
(it moves the corner labels: corners it pushes out of the frame become invisible). An optional
random crop follows the homography: a network that sees 160x120 crops trains ~4x faster on a
CPU and, being fully convolutional, runs unchanged on whole frames. Beyond the paper,
``shadow_edge_p`` (``train.charuconet --shadow-edges``, default 0) then lays on that share of
the images the edge of a cast shadow through a visible corner (`datagen.shadow_edge`), before the
photometric effects: renders seldom put one on a corner, and the point head went silent there.
Every draw comes from the ``rng`` passed in. Images are float32 (H, W) in [0, 1].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from datagen.shadow_edge import random_shadow_edge

PROBABILITIES = {"gaussian_noise": 0.5, "motion_blur": 0.5, "gaussian_blur": 0.25, "speckle": 0.5,
                 "brightness": 0.5, "shadow_or_spotlight": 0.5}


@dataclass(frozen=True)
class AugmentConfig:
    probabilities: tuple[tuple[str, float], ...] = tuple(PROBABILITIES.items())
    homography_p: float = 1.0
    max_motion_kernel: int = 15
    min_brightness: float = 0.02
    crop: tuple[int, int] | None = None  # (width, height) of a random crop, None: whole frames
    crop_on_corner_p: float = 0.75  # how often the crop is placed to hold a random visible corner
    shadow_edge_p: float = 0.0  # share of images with a cast shadow's edge through a visible corner (0: the paper's)


def random_homography(rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    """A 3x3 homography of moderate rotation, scale, shift and perspective about the image centre."""
    centre = np.array([[1, 0, -(width - 1) / 2], [0, 1, -(height - 1) / 2], [0, 0, 1.0]])
    angle = rng.uniform(-math.pi / 6, math.pi / 6)
    scale = math.exp(rng.uniform(math.log(0.7), math.log(1.3)))
    c, s = math.cos(angle) * scale, math.sin(angle) * scale
    similarity = np.array([[c, -s, rng.uniform(-0.15, 0.15) * width], [s, c, rng.uniform(-0.15, 0.15) * height], [0, 0, 1]])
    perspective = np.array([[1, 0, 0], [0, 1, 0], [rng.uniform(-6e-4, 6e-4), rng.uniform(-6e-4, 6e-4), 1.0]])
    return np.linalg.inv(centre) @ similarity @ perspective @ centre


def warp_labels(corners: np.ndarray, visible: np.ndarray, homography: np.ndarray, width: int, height: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """Corners (C, 2) moved by the homography; visibility cleared where they leave the frame."""
    finite = np.all(np.isfinite(corners), axis=1)
    moved = np.full_like(corners, np.nan)
    if finite.any():
        moved[finite] = cv2.perspectiveTransform(corners[finite].reshape(-1, 1, 2).astype(np.float64), homography).reshape(-1, 2)
    inside = finite & (moved[:, 0] >= -0.5) & (moved[:, 0] < width - 0.5) & (moved[:, 1] >= -0.5) & (moved[:, 1] < height - 0.5)
    return moved.astype(np.float32), visible & inside


def crop_origin(rng: np.random.Generator, size: tuple[int, int], crop: tuple[int, int], corners: np.ndarray,
                visible: np.ndarray, on_corner_p: float) -> tuple[int, int]:
    """Top-left pixel (x0, y0) of a ``crop`` (w, h) of an image of ``size`` (W, H): uniform, or with
    probability ``on_corner_p`` uniform among the crops that hold a random visible corner."""
    (width, height), (crop_w, crop_h) = size, crop
    low, high = np.zeros(2), np.array([width - crop_w, height - crop_h], float)
    shown = np.flatnonzero(visible & np.all(np.isfinite(corners), axis=1))
    if len(shown) and rng.random() < on_corner_p:
        x, y = corners[shown[rng.integers(len(shown))]]
        low = np.clip([x - crop_w + 1, y - crop_h + 1], 0, high)
        high = np.clip([x, y], low, high)
    return int(rng.integers(low[0], high[0] + 1)), int(rng.integers(low[1], high[1] + 1))


def crop_labels(corners: np.ndarray, visible: np.ndarray, origin: tuple[int, int], crop: tuple[int, int]
                ) -> tuple[np.ndarray, np.ndarray]:
    """Corners (C, 2) in the crop's pixels; visibility cleared for those outside it."""
    moved = corners - np.asarray(origin, np.float32)
    inside = (moved[:, 0] >= -0.5) & (moved[:, 0] < crop[0] - 0.5) & (moved[:, 1] >= -0.5) & (moved[:, 1] < crop[1] - 0.5)
    return moved, visible & inside & np.all(np.isfinite(moved), axis=1)


def motion_blur(image: np.ndarray, rng: np.random.Generator, max_kernel: int) -> np.ndarray:
    size = int(rng.integers(3, max_kernel + 1)) | 1
    kernel = np.zeros((size, size), np.float32)
    kernel[size // 2, :] = 1.0
    rotation = cv2.getRotationMatrix2D(((size - 1) / 2, (size - 1) / 2), rng.uniform(0, 180), 1.0)
    kernel = cv2.warpAffine(kernel, rotation, (size, size))
    return cv2.filter2D(image, -1, kernel / max(kernel.sum(), 1e-6), borderType=cv2.BORDER_REFLECT)


def shadow_or_spotlight(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Multiply by a soft-edged dark polygon (a cast shadow) or a bright ellipse in darkness (a spot)."""
    height, width = image.shape
    mask = np.zeros((height, width), np.float32)
    if rng.random() < 0.5:
        centre = rng.uniform(0, 1, 2) * (width, height)
        points = centre + rng.normal(0, 0.35, (int(rng.integers(3, 8)), 2)) * (width, height)
        cv2.fillPoly(mask, [points.astype(np.int32)], 1.0)
        mask = cv2.GaussianBlur(mask, (0, 0), rng.uniform(1, 15))
        return image * (1.0 - rng.uniform(0.3, 0.9) * mask)
    centre = tuple(int(v) for v in rng.uniform(0, 1, 2) * (width, height))
    axes = tuple(int(v) for v in rng.uniform(0.15, 0.6, 2) * (width, height))
    cv2.ellipse(mask, centre, axes, rng.uniform(0, 180), 0, 360, 1.0, -1)
    mask = cv2.GaussianBlur(mask, (0, 0), rng.uniform(3, 25))
    ambient = rng.uniform(0.05, 0.5)
    return image * (ambient + (1.0 - ambient) * mask)


def shadow_edge_through_corner(image: np.ndarray, corners: np.ndarray, visible: np.ndarray, rng: np.random.Generator,
                               probability: float) -> np.ndarray:
    """With ``probability``, ``image`` (H, W) under a cast shadow's edge passing near a random visible corner of
    ``corners`` (C, 2); unchanged when none is visible."""
    shown = np.flatnonzero(visible & np.all(np.isfinite(corners), axis=1))
    if not len(shown) or rng.random() >= probability:
        return image
    return random_shadow_edge(image, corners[shown[rng.integers(len(shown))]], rng)


def photometric(name: str, image: np.ndarray, rng: np.random.Generator, config: AugmentConfig) -> np.ndarray:
    if name == "gaussian_noise":
        return image + rng.normal(0.0, rng.uniform(0.005, 0.08), image.shape).astype(np.float32)
    if name == "motion_blur":
        return motion_blur(image, rng, config.max_motion_kernel)
    if name == "gaussian_blur":
        return cv2.GaussianBlur(image, (0, 0), rng.uniform(0.5, 2.5))
    if name == "speckle":
        return image * (1.0 + rng.normal(0.0, rng.uniform(0.02, 0.3), image.shape)).astype(np.float32)
    if name == "brightness":
        return image * math.exp(rng.uniform(math.log(config.min_brightness), 0.0))
    if name == "shadow_or_spotlight":
        return shadow_or_spotlight(image, rng)
    raise ValueError(f"unknown augmentation {name!r}")


def augment(image: np.ndarray, corners: np.ndarray, visible: np.ndarray, has_board: bool, rng: np.random.Generator,
            config: AugmentConfig = AugmentConfig()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(image float32 (H, W) in [0, 1], corners (C, 2), visible (C,)) -> the augmented triple
    ((h, w) = ``config.crop`` reversed when cropping)."""
    height, width = image.shape
    image = image.astype(np.float32)
    if has_board and rng.random() < config.homography_p:
        homography = random_homography(rng, width, height)
        # Replicate, not reflect: a mirrored board beyond the edge would show corners without labels.
        image = cv2.warpPerspective(image, homography, (width, height), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        corners, visible = warp_labels(corners, visible, homography, width, height)
    if config.crop is not None:
        if config.crop[0] > width or config.crop[1] > height:
            raise ValueError(f"crop {config.crop[0]}x{config.crop[1]} is larger than the {width}x{height} frames")
        x0, y0 = crop_origin(rng, (width, height), config.crop, corners, visible, config.crop_on_corner_p)
        image = image[y0:y0 + config.crop[1], x0:x0 + config.crop[0]]
        corners, visible = crop_labels(corners, visible, (x0, y0), config.crop)
    if config.shadow_edge_p:  # no draw at 0: runs without it augment as they always did
        image = shadow_edge_through_corner(image, corners, visible, rng, config.shadow_edge_p)
    effects = list(config.probabilities)
    for index in rng.permutation(len(effects)):
        name, probability = effects[index]
        if rng.random() < probability:
            image = photometric(name, image, rng, config)
    return np.clip(image, 0.0, 1.0), corners, visible
