"""Exceptions with messages that name the problem and the fix."""


class DeepCharucoError(Exception):
    """Base class of every error this package raises on bad input."""


class BoardSpecError(DeepCharucoError, ValueError):
    """An invalid or unreadable board description."""


class ImageError(DeepCharucoError, ValueError):
    """An image a detector cannot take (dtype, shape, empty)."""


class CameraFileError(DeepCharucoError, ValueError):
    """A missing or malformed camera intrinsics file, or bad intrinsics."""


class OptionError(DeepCharucoError, ValueError):
    """An option given a value it does not take (`deepcharuco.core.checks.check_choice` names the choices)."""


class ShapeError(DeepCharucoError, ValueError):
    """An array of the wrong shape or with non-finite values (`deepcharuco.core.checks.check_shape`)."""


class ExportError(DeepCharucoError, ValueError):
    """A calibration that a file format cannot hold (a rational model in Kalibr's radtan), or a rectification asked
    of cameras that have none (not a pair, two image sizes)."""
