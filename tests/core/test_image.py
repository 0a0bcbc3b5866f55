"""The image contract at the API edge: what to_gray_u8 takes, and what it tells the user to do otherwise."""

import re

import cv2
import numpy as np
import pytest

from deepcharuco import BoardSpec, OpenCVDetector
from deepcharuco.core.errors import ImageError
from deepcharuco.core.image import to_gray_u8


def suggested_conversion(message: str) -> str:
    """The first Python expression the error message suggests (between 'it: ' and ' for')."""
    return re.search(r"not clip it: (.+?) for ", message)[1]


def test_a_16_bit_image_gets_a_hint_that_scales_it(default_views):
    """The hint's conversion, applied to a 16-bit copy of a view, gives back the view the detector finds
    the board in; clipping (the old hint) would give a white image."""
    image = default_views[0][0]
    deep = image.astype(np.uint16) * 257  # the same view, 16-bit (0..65535)
    with pytest.raises(ImageError) as refused:
        to_gray_u8(deep)
    message = str(refused.value)
    assert "np.clip" not in message and "convertScaleAbs" in message
    converted = eval(suggested_conversion(message), {"np": np, "cv2": cv2, "img": deep})
    np.testing.assert_array_equal(converted, image)
    assert len(OpenCVDetector(BoardSpec()).detect(converted)) == 16
    clipped = np.clip(deep, 0, 255).astype(np.uint8)  # the old advice: every pixel brighter than black turns white
    assert len(OpenCVDetector(BoardSpec()).detect(clipped)) < 16


def test_other_types_are_refused_with_their_own_hint():
    messages = {}
    for dtype in (np.float32, np.int16, bool):
        with pytest.raises(ImageError) as refused:
            to_gray_u8(np.ones((4, 4), dtype))
        messages[dtype] = str(refused.value)
    assert "(img * 255).round()" in messages[np.float32] and "cv2.normalize" in messages[np.int16]
    assert "np.clip" not in "".join(messages.values())
    assert to_gray_u8(np.zeros((4, 4, 3), np.uint8)).shape == (4, 4)
