"""The image contract at the API edge: detectors take uint8 grayscale HxW."""

from __future__ import annotations

import cv2
import numpy as np

from deepcharuco.core.errors import ImageError


def to_gray_u8(image: np.ndarray) -> np.ndarray:
    """Validate an image and return it as a contiguous uint8 (H, W) array.

    Accepts uint8 (H, W), (H, W, 1), BGR (H, W, 3) or BGRA (H, W, 4) as OpenCV reads them;
    colour is converted with OpenCV's BGR weights. Anything else raises `ImageError`, whose
    message says how to convert: other bit depths are never converted here, because the right
    scale depends on the camera (a 16-bit PNG spans 0..65535, a 12-bit sensor in uint16 0..4095),
    and clipping to [0, 255] would turn most of such an image white.
    """
    if not isinstance(image, np.ndarray):
        raise ImageError(f"expected a numpy array image, got {type(image).__name__}")
    if image.size == 0:
        raise ImageError(f"the image is empty (shape {image.shape}); check that it was read correctly")
    if image.dtype != np.uint8:
        raise ImageError(f"expected a uint8 image, got dtype {image.dtype}{_conversion_hint(image.dtype)}")
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


def _conversion_hint(dtype: np.dtype) -> str:
    """How to bring an image of ``dtype`` to uint8 by scaling its range (never by clipping it)."""
    if np.issubdtype(dtype, np.floating):
        return " (scale a [0, 1] float image with (img * 255).round().astype(np.uint8))"
    if np.issubdtype(dtype, np.unsignedinteger):
        bits = np.iinfo(dtype).bits
        return (f" (scale it, do not clip it: (img >> {bits - 8}).astype(np.uint8) for the full {bits}-bit range, "
                f"or cv2.convertScaleAbs(img, alpha=255 / img.max()) for data that uses less, e.g. a 12-bit sensor)")
    if np.issubdtype(dtype, np.signedinteger):
        return " (scale it, do not clip it: cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX, cv2.CV_8U))"
    return " (convert it to a uint8 grayscale or BGR image)"
