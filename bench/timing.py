"""``time_call``: the median wall time of a call, after a warm-up (the benchmarks' one way to time)."""

from __future__ import annotations

import statistics
import time


def time_call(fn, repeats: int, warmup: int = 1) -> dict:
    """{"median_ms", "min_ms", "repeats"} of ``repeats`` calls of ``fn`` after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return {"median_ms": 1e3 * statistics.median(times), "min_ms": 1e3 * min(times), "repeats": repeats}
