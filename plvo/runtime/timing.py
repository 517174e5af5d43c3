"""Per-stage timing of a run: a clock for one step's stages, and the summary of a run's timings."""

from __future__ import annotations

import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np


@dataclass
class StageClock:
    """Seconds by stage within one step; a stage timed twice adds up."""

    seconds: dict[str, float] = field(default_factory=dict)

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0

    def add(self, name: str, seconds: float) -> None:
        self.seconds[name] = self.seconds.get(name, 0.0) + seconds


def timing_summary(timings: Mapping[str, Sequence[float]]) -> dict[str, dict[str, float]]:
    """Per stage: runs, mean, median, 90th percentile and max milliseconds, total seconds."""
    out = {}
    for name, values in timings.items():
        v = np.asarray(values)
        out[name] = {
            "runs": int(v.size),
            "mean_ms": float(v.mean() * 1e3),
            "median_ms": float(np.median(v) * 1e3),
            "p90_ms": float(np.percentile(v, 90) * 1e3),
            "max_ms": float(v.max() * 1e3),
            "total_s": float(v.sum()),
        }
    return out
