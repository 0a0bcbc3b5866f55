"""What every layer of the runtime shares: its errors and option checks, the `Detection` every detector returns,
image checks, safe output files, the operating system's answers, OpenCV version shims and stage timers.

Nothing here imports another subpackage of ``deepcharuco``.
"""

from deepcharuco.core.checks import check_choice, check_shape
from deepcharuco.core.detection import Detection
from deepcharuco.core.errors import (BoardSpecError, CameraFileError, DeepCharucoError, ImageError, OptionError,
                                     ShapeError)
from deepcharuco.core.files import OutputError, write_atomic
from deepcharuco.core.image import to_gray_u8

__all__ = ["check_choice", "check_shape", "Detection", "BoardSpecError", "CameraFileError", "DeepCharucoError",
           "ImageError", "OptionError", "ShapeError", "OutputError", "write_atomic", "to_gray_u8"]
