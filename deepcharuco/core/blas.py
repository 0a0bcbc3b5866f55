"""numpy's BLAS on one thread: small matrices run faster there, and no idle BLAS worker holds a core.

OpenBLAS (numpy's) starts a worker per core and, after a call, lets them spin for milliseconds:
- a network run next in ONNX Runtime's 2-thread pool waits for the core a spinning worker holds: on the 11x8 board
  at 320x240 (AVX2 host, fresh processes) RefineNet took 11 ms a frame instead of 6, a frame 40-49 ms instead of
  34-36 (the detector's decoding, whose matrices are small, runs single-threaded: `Detector.detect`);
- on a loaded 2-core machine a batched inverse of 30 6 x 6 matrices (a calibration's views, `weighting`) took 10-13 ms
  threaded against 0.1 ms on one thread: a camera's weighed calibration spent 6 s there instead of 0.1 s.
"""

from __future__ import annotations

from functools import cache
from typing import ContextManager

from threadpoolctl import ThreadpoolController


@cache
def _numpy_blas() -> ThreadpoolController:
    return ThreadpoolController().select(user_api="blas")


def single_threaded_blas() -> ContextManager:
    """A context in which numpy's BLAS runs on the calling thread alone, restored on exit."""
    return _numpy_blas().limit(limits=1)
