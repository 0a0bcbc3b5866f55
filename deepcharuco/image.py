"""The image contract at the API edge: detectors take uint8 grayscale HxW."""

from __future__ import annotations

import cv2
import numpy as np

from deepcharuco.errors import ImageError


def to_gray_u8(image: np.ndarray) -> np.ndarray:
    """Validate an image and return it as a contiguous uint8 (H, W) array.

    Accepts uint8 (H, W), (H, W, 1), BGR (H, W, 3) or BGRA (H, W, 4) as OpenCV reads them;
    colour is converted with OpenCV's BGR weights. Anything else raises `ImageError`.
    """
    if not isinstance(image, np.ndarray):
        raise ImageError(f"expected a numpy array image, got {type(image).__name__}")
    if image.size == 0:
        raise ImageError(f"the image is empty (shape {image.shape}); check that it was read correctly")
    if image.dtype != np.uint8:
        hint = (
            " (scale a [0, 1] float image with (img * 255).round().astype(np.uint8))"
            if np.issubdtype(image.dtype, np.floating)
            else " (convert with cv2.convertScaleAbs or np.clip(img, 0, 255).astype(np.uint8))"
        )
        raise ImageError(f"expected a uint8 image, got dtype {image.dtype}{hint}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    elif image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    if image.ndim != 2:
        raise ImageError(
            f"expected a grayscale (H, W) or BGR (H, W, 3) image, got shape {image.shape}"
        )
    return np.ascontiguousarray(image)
