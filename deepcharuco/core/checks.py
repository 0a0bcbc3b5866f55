"""One check for an option's value and one for an array's shape, so that every function refuses bad input
with the same kind of error and message (Kornia's ``core/check.py`` is the model)."""

from __future__ import annotations

from typing import Any, Iterable

import numpy as np

from deepcharuco.core.errors import OptionError, ShapeError


def check_choice(name: str, value: Any, choices: Iterable[Any]) -> Any:
    """Return ``value`` if it is one of ``choices``.

    Raises:
        OptionError: (a ``ValueError``) naming the option, the value given and the choices.

    Example:
        >>> check_choice("refine", "subpix", ("refinenet", "subpix", "none"))
        'subpix'
        >>> check_choice("refine", "sub", ("refinenet", "subpix", "none"))
        Traceback (most recent call last):
        ...
        deepcharuco.core.errors.OptionError: refine must be one of ('refinenet', 'subpix', 'none'), got 'sub'
    """
    choices = tuple(choices)
    if value not in choices:
        raise OptionError(f"{name} must be one of {choices}, got {value!r}")
    return value


def check_shape(array: Any, shape: tuple[int | None, ...], name: str, finite: bool = True) -> np.ndarray:
    """``array`` as a float64 array of ``shape`` (``None``: any length on that axis), finite unless ``finite=False``.

    Raises:
        ShapeError: (a ``ValueError``) naming the array, the shape expected and the shape given, or saying that
            it holds NaN or infinity.

    Example:
        >>> check_shape([[800, 0, 320], [0, 800, 240], [0, 0, 1]], (3, 3), "K").shape
        (3, 3)
        >>> check_shape([800, 800, 320, 240], (3, 3), "K")
        Traceback (most recent call last):
        ...
        deepcharuco.core.errors.ShapeError: K must have shape (3, 3), got (4,)
    """
    try:
        values = np.asarray(array, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise ShapeError(f"{name} must be a numeric array of shape {shape}: {error}") from None
    if values.ndim != len(shape) or any(want is not None and got != want for got, want in zip(values.shape, shape)):
        expected = "(" + ", ".join("N" if want is None else str(want) for want in shape) + ("," if len(shape) == 1 else "") + ")"
        raise ShapeError(f"{name} must have shape {expected}, got {values.shape}")
    if finite and not np.isfinite(values).all():
        raise ShapeError(f"{name} holds NaN or infinite values")
    return values
