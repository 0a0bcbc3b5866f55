"""The CPU a timing was taken on, named in every timing table.

Frames per second from different CPUs do not compare: this project's own 2-core VM once came up on an
AMD EPYC with AVX2 only, where OpenCV and the deep detector both ran at 0.5-0.8x their earlier fps
(README, "Speed"). A table that names the CPU and its widest vector extension says which of its numbers
may be set beside which.
"""

from __future__ import annotations

import platform
from pathlib import Path

CPUINFO = Path("/proc/cpuinfo")
# Widest first: the first one a CPU has is the one named.
VECTOR_EXTENSIONS = (("avx512_vnni", "AVX-512 VNNI"), ("avx512f", "AVX-512"), ("avx2", "AVX2"), ("avx", "AVX"),
                     ("sse4_2", "SSE4.2"), ("asimd", "NEON"))


def cpu_description(cpuinfo: str | None = None) -> str:
    """The CPU's model name and widest vector extension, e.g. ``"AMD EPYC (x86_64, AVX2)"``, read from
    ``cpuinfo`` (the text of Linux's /proc/cpuinfo; default: that file where it exists); where it says
    neither, Python's ``platform`` names the architecture alone."""
    if cpuinfo is None:
        try:
            cpuinfo = CPUINFO.read_text(errors="replace")
        except OSError:
            cpuinfo = ""
    fields: dict[str, str] = {}
    for line in cpuinfo.splitlines():
        key, colon, value = line.partition(":")
        if colon:
            fields.setdefault(key.strip().lower(), value.strip())
    machine = platform.machine()
    name = fields.get("model name") or fields.get("cpu model") or platform.processor() or machine or "CPU"
    flags = set((fields.get("flags") or fields.get("features") or "").split())
    details = [machine] if machine and machine not in name else []
    details += [label for flag, label in VECTOR_EXTENSIONS if flag in flags][:1]
    return f"{name} ({', '.join(details)})" if details else name


def gpu_name(device: str) -> str:
    """The accelerator behind a PyTorch ``device`` ("cuda", "cuda:1", "mps"), e.g. ``"NVIDIA H200"``; the device
    string itself where PyTorch cannot name it."""
    import torch

    if device.startswith("cuda") and torch.cuda.is_available():
        return torch.cuda.get_device_name(torch.device(device))
    return device
