"""Wall time of a detection's stages, for benchmarks and profiles.

    with StageTimes() as times:
        detector.detect(image)
    times.seconds   # {"network 0": 0.004, "candidates": 0.0002, "board check": 0.001, ...}

Stages are timed only while a `StageTimes` is active (a module-level check otherwise: no cost a user
meets). Only stages on the detecting thread are wrapped: RefineNet started on a background thread counts
where its result is waited for.
"""

from __future__ import annotations

import time
from collections import defaultdict
from contextlib import contextmanager

_active: StageTimes | None = None


class StageTimes:
    """Seconds and call counts per stage name, summed over every detection run while it is active;
    ``counts`` also holds the tallies `tally` adds (candidates per level ...)."""

    def __init__(self):
        self.seconds: dict[str, float] = defaultdict(float)
        self.counts: dict[str, int] = defaultdict(int)
        self._previous: StageTimes | None = None

    def __enter__(self) -> StageTimes:
        global _active
        self._previous, _active = _active, self
        return self

    def __exit__(self, *exc) -> None:
        global _active
        _active = self._previous


@contextmanager
def stage(name: str):
    """Times the block as stage ``name`` in the active `StageTimes` (nothing when none is active)."""
    times = _active
    if times is None:
        yield
        return
    started = time.perf_counter()
    try:
        yield
    finally:
        times.seconds[name] += time.perf_counter() - started
        times.counts[name] += 1


def tally(name: str, amount: int = 1) -> None:
    """Adds ``amount`` to the active `StageTimes`' count ``name`` (nothing when none is active)."""
    if _active is not None:
        _active.counts[name] += int(amount)
