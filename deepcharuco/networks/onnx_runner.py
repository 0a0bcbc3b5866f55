"""The networks on ONNX Runtime (CPU), from serialized ONNX models: no PyTorch needed.

`OnnxRunner` runs ChArUcoNet and RefineNet and returns numpy arrays, the `deepcharuco.networks.runtime.Runner`
protocol; `deepcharuco.networks.runtime` makes one from networks loaded with PyTorch (exported in memory), the
`Detector` from a shipped ONNX bundle (`deepcharuco.networks.onnx_bundle`) where PyTorch is not installed.

Threads: each network runs on as many threads as PyTorch would (`network_threads`; idle workers sleep);
`OnnxRunner.refinenet_in_background` runs RefineNet on one thread of its own while the caller's numpy
decoding holds the other core (`levels.EarlyRefinement`), and the detector runs numpy's BLAS on one
thread (`deepcharuco.core.blas`): its spinning workers would take that core from the networks.
"""

from __future__ import annotations

import importlib.util
import os
import sys
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable

import numpy as np
from deepcharuco.core.platform import available_cpus


def onnxruntime_available() -> bool:
    return importlib.util.find_spec("onnxruntime") is not None


def network_threads() -> int:
    """Threads a network runs on: PyTorch's count where PyTorch is loaded (``torch.get_num_threads()``, which
    follows OMP_NUM_THREADS), else OMP_NUM_THREADS, else the CPUs this process may use."""
    torch = sys.modules.get("torch")
    if torch is not None:
        return torch.get_num_threads()
    if os.environ.get("OMP_NUM_THREADS", "").isdigit() and int(os.environ["OMP_NUM_THREADS"]) > 0:
        return int(os.environ["OMP_NUM_THREADS"])
    return available_cpus()


def _session(model: bytes, threads: int):
    import onnxruntime

    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.graph_optimization_level = onnxruntime.GraphOptimizationLevel.ORT_ENABLE_ALL
    # Idle workers sleep instead of spinning: as fast on an idle CPU (8.7 vs 8.5 ms at 320x240, 2 threads) and
    # far faster beside other work (18 vs 28 ms with one other busy process on 2 cores).
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return onnxruntime.InferenceSession(model, options, providers=["CPUExecutionProvider"])


class OnnxRunner:
    """ONNX Runtime on the CPU: ChArUcoNet from ``charuconet_model`` (serialized ONNX: both heads, or the point
    head alone, or the int8 model) and RefineNet from ``refinenet_model`` (None: no RefineNet)."""

    def __init__(self, charuconet_model: bytes, refinenet_model: bytes | None, name: str = "onnx",
                 threads: int | None = None):
        self.name = name
        threads = threads or network_threads()
        self._charuconet = _session(charuconet_model, threads)
        self._charuconet_input = self._charuconet.get_inputs()[0].name
        self._refinenet = self._refinenet_one_thread = None
        if refinenet_model is not None:
            self._refinenet = _session(refinenet_model, threads)
            self._refinenet_input = self._refinenet.get_inputs()[0].name
            if threads > 1:
                self._refinenet_one_thread = _session(refinenet_model, 1)
        self._background = BackgroundThread()

    @property
    def charuconet_session(self):
        return self._charuconet

    @property
    def refinenet_session(self):
        return self._refinenet

    def charuconet(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        points, *ids = self._charuconet.run(None, {self._charuconet_input: image})
        return points[0], ids[0][0] if ids else None

    def refinenet(self, patches: np.ndarray) -> np.ndarray:
        (logits,) = self._refinenet.run(None, {self._refinenet_input: patches})
        return logits

    def refinenet_in_background(self, patches: np.ndarray) -> Future | None:
        if self._refinenet_one_thread is None:
            return None  # one thread in all: nothing runs beside the caller

        def run() -> np.ndarray:
            (logits,) = self._refinenet_one_thread.run(None, {self._refinenet_input: patches})
            return logits

        return self._background.submit(run)


class BackgroundThread:
    """One worker thread, made on first use and again in a forked child (which has none of its parent's threads:
    a `ThreadPoolExecutor` inherited across a fork would queue work that never runs)."""

    def __init__(self):
        self._pid: int | None = None
        self._executor: ThreadPoolExecutor | None = None

    def submit(self, function: Callable[[], np.ndarray]) -> Future:
        if self._pid != os.getpid():
            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="deepcharuco-background")
            self._pid = os.getpid()
        return self._executor.submit(function)
