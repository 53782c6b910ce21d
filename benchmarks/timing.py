"""Timing helpers: median and p99 over many repetitions after warm-up; machine description."""

from __future__ import annotations

import datetime as _dt
import os
import platform
import resource
import time
from collections.abc import Callable

import numpy as np


def time_calls(fn: Callable[[int], object], n: int, warmup: int = 50) -> dict:
    """Call ``fn(i)`` for i in range(warmup + n); per-call wall time in microseconds."""
    for i in range(warmup):
        fn(i)
    t = np.empty(n)
    clock = time.perf_counter_ns
    for i in range(n):
        t0 = clock()
        fn(warmup + i)
        t[i] = clock() - t0
    t /= 1e3
    return {"n": n, "median_us": float(np.median(t)), "p99_us": float(np.percentile(t, 99)),
            "mean_us": float(t.mean())}


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def machine() -> dict:
    cpu = platform.processor()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    import scipy

    return {
        "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "cpu": cpu, "cores": os.cpu_count(), "platform": platform.platform(),
        "python": platform.python_version(), "numpy": np.__version__, "scipy": scipy.__version__,
    }


def table(rows: list[dict], columns: list[str], title: str = "") -> str:
    def fmt(v):
        if isinstance(v, float):
            return f"{v:.3g}" if abs(v) < 1e4 else f"{v:.0f}"
        return str(v)

    cells = [[fmt(r.get(c, "")) for c in columns] for r in rows]
    widths = [max(len(c), *(len(row[i]) for row in cells)) if cells else len(c) for i, c in enumerate(columns)]
    lines = [title] if title else []
    lines.append("  ".join(c.ljust(w) for c, w in zip(columns, widths, strict=True)))
    lines.append("  ".join("-" * w for w in widths))
    lines += ["  ".join(v.ljust(w) for v, w in zip(row, widths, strict=True)) for row in cells]
    return "\n".join(lines)
