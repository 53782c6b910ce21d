"""Per-frame solve latency of every registered mode at film-rig scales (54x50, 72x150, 72x1000).

Each mode is timed on the same synthetic stream; the ratio column compares it with plain
unconstrained least squares (a prefactored pseudo-inverse product) measured in the same run.
"""

from __future__ import annotations

import numpy as np

from benchmarks.synthetic import synthetic_profile, synthetic_stream
from benchmarks.timing import table, time_calls
from livecap.modes import MODES, build_solver

SIZES = [(54, 50), (72, 150), (72, 1000)]
# options some modes need to run on a bare profile (keys for RBF are drawn from the stream)
MODE_OPTIONS: dict[str, dict] = {}
# scipy's BVLS behind "lsq" takes milliseconds per frame (and far more when m > 3n): fewer calls
SLOW_COUNTS = {"lsq": {50: 300, 150: 200, 1000: 10}}


def _baseline(profile, targets) -> dict:
    pinv = np.linalg.pinv(profile.basis)
    flat = targets.reshape(len(targets), -1)
    return time_calls(lambda i: pinv @ flat[i % len(flat)], n=2000, warmup=100)


def run(quick: bool = False) -> dict:
    rows = []
    n_frames = 300 if quick else 3000
    for n, m in SIZES:
        profile = synthetic_profile(n, m)
        targets, valid, W = synthetic_stream(profile, n_frames)
        base = _baseline(profile, targets)
        rows.append({"mode": "pinv (baseline)", "size": f"{n}x{m}", **base, "ratio_p99": 1.0})
        for mode in sorted(MODES):
            opts = dict(MODE_OPTIONS.get(mode, {}))
            if callable(opts.get("prepare")):
                opts = opts["prepare"](profile, targets, W)
            try:
                solver = build_solver(mode, profile, opts)
            except Exception as exc:  # a mode that cannot be built on a bare profile is reported, not hidden
                rows.append({"mode": mode, "size": f"{n}x{m}", "error": str(exc)[:60]})
                continue
            count = SLOW_COUNTS.get(mode, {}).get(m, 200 if quick else 2000)
            if quick:
                count = min(count, 200)
            res = time_calls(lambda i, s=solver, x=targets, v=valid: s.step(x[i % n_frames], v[i % n_frames]),
                             n=count, warmup=50)
            rows.append({"mode": mode, "size": f"{n}x{m}", **res, "ratio_p99": res["p99_us"] / base["p99_us"]})
    print(table(rows, ["mode", "size", "median_us", "p99_us", "ratio_p99", "n", "error"],
                "Per-frame solve latency (us); ratio = p99 / p99 of the prefactored pinv product"))
    return {"rows": rows}
