"""Timing helpers: median and p99 over many repetitions after warm-up; machine description."""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import resource
import time
from collections.abc import Callable
from pathlib import Path

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


def suite_main(run: Callable[..., dict], doc: str, **lists: str) -> int:
    """A suite run on its own (``python -m benchmarks.NAME``): ``--quick``, ``--json FILE``, and
    each keyword as a comma-separated option handed to ``run`` (e.g. ``modes="qp,rbf"``)."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer repetitions (a smoke run)")
    ap.add_argument("--json", help="also write the figures to this JSON file")
    for name, default in lists.items():
        ap.add_argument(f"--{name}", default=default, help=f"comma-separated (default {default})")
    args = ap.parse_args()
    out = run(args.quick, **{name: tuple(getattr(args, name).split(",")) for name in lists})
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(out, indent=1, default=float))
        print(f"written {args.json}")
    return 0
