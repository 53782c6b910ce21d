"""Movement-matching benchmark: offline solve vs the literal sparse Eq. 5 and Seol's Table I, edit
re-solve (12-frame range and whole 1000-frame take), streaming per-frame latency, the cost of rig
limits, and drift on a long stream.

    python -m benchmarks.movement [--quick]

``run(quick)`` prints a table and returns the figures as a dict (the suite writes them as JSON).
Sizes follow Seol et al. 2012 Table I (54 markers, 50 shapes) and the issue (72 x 150 streaming).
"""

from __future__ import annotations

import os
import platform
import sys
import time

import numpy as np

from benchmarks.timing import suite_main
from livecap.offline.metrics import drift, velocity_error
from solvers.movement import Edit, MovementMatching
from solvers.prior import PCAPrior
from solvers.reference import solve_reference
from solvers.streaming import StreamingMovement

SEOL_TABLE_I = {10: 0.22, 50: 1.32, 100: 2.76, 500: 15.21, 1000: 31.65, 1500: 47.38}  # seconds, Matlab


def _smooth(rng: np.random.Generator, T: int, m: int, width: float = 10.0) -> np.ndarray:
    k = np.exp(-0.5 * (np.arange(-40, 41) / width) ** 2)
    X = rng.normal(size=(T + 100, m))
    Y = np.array([np.convolve(X[:, j], k / k.sum(), mode="same") for j in range(m)]).T[50:50 + T]
    return np.clip(0.3 + 3.0 * Y, 0.0, 1.0) * (rng.random(m) < 0.4)


def _problem(rng, T: int, n: int, m: int, noise: float = 0.3):
    B = rng.normal(scale=2.0, size=(3 * n, m))
    W = _smooth(rng, T, m)
    return B, W, (W @ B.T).reshape(T, n, 3) + rng.normal(0, noise, (T, n, 3))


def _best(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def offline(quick: bool) -> list[dict]:
    rng = np.random.default_rng(0)
    n, m = 54, 50
    rows = []
    for T in ([10, 50, 100] if quick else list(SEOL_TABLE_I)):
        B, _, S = _problem(rng, T, n, m)
        prior = PCAPrior.from_shapes(B)
        mm = MovementMatching(B, alpha=0.01, prior=prior)  # Seol's alpha, neutral at both ends
        W = mm.solve(S)
        ours = _best(lambda B=B, prior=prior, S=S: MovementMatching(B, alpha=0.01, prior=prior).solve(S), 5)
        solve_only = _best(lambda mm=mm, S=S: mm.solve(S), 5)
        row = {"frames": T, "ours_s": ours, "ours_solve_only_s": solve_only, "seol_matlab_s": SEOL_TABLE_I[T]}
        if T <= (100 if quick else 500):  # the literal form needs ~1 GB beyond 500 frames
            bounds = mm.boundary_frames(S, np.ones((T, n), bool))
            t0 = time.perf_counter()
            R = solve_reference(B, S, bounds, alpha=0.01, prior=prior)
            row["reference_s"] = time.perf_counter() - t0
            row["max_abs_diff"] = float(np.abs(W - R).max())
        rows.append(row)
    return rows


def edit_resolve(quick: bool = False) -> dict:
    """Spacetime edit re-solve (Seol et al. 2012 §6) on a 1000-frame take at 54 x 50: a 12-frame
    propagation range, and the whole take as the range; next to re-solving the take from scratch."""
    rng = np.random.default_rng(1)
    B, _, S = _problem(rng, 1000, 54, 50)
    mm = MovementMatching(B, alpha=0.01, prior=PCAPrior.from_shapes(B))
    W = mm.solve(S)
    reps = 10 if quick else 50
    out = {"take_frames": 1000, "size": "54x50"}
    for label, rng_ in (("range12", (494, 506)), ("whole", None)):
        edit = [Edit(500, {3: 0.9, 7: 0.2}, rng_)]
        out[f"{label}_s"] = _best(lambda edit=edit: mm.edit(W, edit), reps)
        out[f"{label}_with_targets_s"] = _best(lambda edit=edit: mm.edit(W, edit, S), max(3, reps // 5))
    out["full_resolve_s"] = _best(lambda: mm.solve(S), max(3, reps // 10))
    # back-compatible keys
    out["range_frames"], out["edit_s"], out["edit_with_targets_s"] = 12, out["range12_s"], out["range12_with_targets_s"]
    return out


def streaming_latency(quick: bool) -> dict:
    """Per-frame ``step`` latency of the sliding-window solver at 72 markers x 150 shapes (the issue's
    size; goal p99 <= 50 us), warm, over thousands of frames. The baseline is the cheapest per-frame
    solve there is, unconstrained least squares as one prefactored pseudo-inverse product, timed in
    the same loop on the same frame (alternating which goes first) so both see the same load; the
    ratios are stream / baseline."""
    rng = np.random.default_rng(2)
    n, m = 72, 150
    T = 3000 if quick else 20000
    B, _, S = _problem(rng, T, n, m)
    flat = S.reshape(T, -1)
    pinv = np.linalg.pinv(B)
    prior = PCAPrior.from_shapes(B)
    clock, cpu_clock = time.perf_counter_ns, time.thread_time_ns
    out = {}
    for K, L, miss in ((24, 0, 0.0), (24, 4, 0.0), (24, 4, 0.05)):
        st = StreamingMovement(B, np.zeros(m), np.ones(m), window=K, lookahead=L, alpha=0.5, prior=prior, beta=0.1)
        valid = rng.random((T, n)) > miss
        for i in range(200):
            st.step(S[i], valid[i])
            pinv @ flat[i]
        wall, cpu, base = np.empty(T), np.empty(T), np.empty(T)
        for i in range(T):
            if i % 2:
                t0 = clock()
                pinv @ flat[i]
                base[i] = clock() - t0
            c0, t0 = cpu_clock(), clock()
            st.step(S[i], valid[i])
            t1 = clock()
            cpu[i], wall[i] = cpu_clock() - c0, t1 - t0
            if not i % 2:
                t0 = clock()
                pinv @ flat[i]
                base[i] = clock() - t0
        p50, p99 = (float(np.percentile(wall, q) / 1e3) for q in (50, 99))
        b50, b99 = (float(np.percentile(base, q) / 1e3) for q in (50, 99))
        out[f"K{K}_L{L}_missing{int(miss * 100)}%"] = {
            "frames": T, "p50_us": p50, "p99_us": p99,
            "cpu_p50_us": float(np.percentile(cpu, 50) / 1e3), "cpu_p99_us": float(np.percentile(cpu, 99) / 1e3),
            "baseline_pinv_p50_us": b50, "baseline_pinv_p99_us": b99, "ratio_p50": p50 / b50, "ratio_p99": p99 / b99,
            "goal_p99_us": 50.0, "load_avg": os.getloadavg()[0]}
    return out


def limits_and_drift(quick: bool) -> dict:
    """Velocity-error cost of clipping to the rig limits, and error growth over a long stream."""
    rng = np.random.default_rng(3)
    rate, n, m = 120.0, 54, 50
    T = int(rate * (120 if quick else 300))
    B = rng.normal(scale=2.0, size=(3 * n, m))
    truth = np.vstack([_smooth(rng, 600, m) for _ in range(T // 600)])
    truth = np.clip(truth * 1.2, 0, 1.2)  # the actor goes a little past the rig's extremes
    S = (truth @ B.T).reshape(T, n, 3) + rng.normal(0, 0.3, (T, n, 3))
    valid = rng.random((T, n)) > 0.02
    prior = PCAPrior.from_shapes(B)
    kw = dict(window=24, lookahead=4, alpha=0.5, prior=prior, beta=0.1)
    t0 = time.perf_counter()
    W_clip = StreamingMovement(B, np.zeros(m), np.ones(m), limits="clip", **kw).solve(S, valid)
    seconds = time.perf_counter() - t0
    W_free = StreamingMovement(B, np.zeros(m), np.ones(m), limits="none", **kw).solve(S, valid)
    v_clip, v_free = velocity_error(B, W_clip, S, valid), velocity_error(B, W_free, S, valid)
    err = np.sqrt(np.mean((W_clip - np.clip(truth, 0, 1)) ** 2, axis=1))
    first, last = drift(err, rate)
    return {"stream_seconds": T / rate, "solve_s": seconds, "velocity_error_clip": v_clip,
            "velocity_error_unclipped": v_free, "clip_extra_percent": (v_clip - v_free) / v_free * 100,
            "weight_rmse_first_minute": first, "weight_rmse_last_minute": last}


def run(quick: bool = False) -> dict:
    machine = f"{platform.machine()} {platform.processor() or ''} {os.cpu_count()} cpus, load {os.getloadavg()[0]:.1f}"
    res = {"machine": machine.strip(), "offline": offline(quick), "edit": edit_resolve(quick),
           "streaming_72x150": streaming_latency(quick), "limits_drift": limits_and_drift(quick)}
    print(f"movement matching benchmark ({res['machine']})")
    print(f"{'frames':>7} {'ours ms':>9} {'solve ms':>9} {'literal Eq.5 s':>15} {'Seol Matlab s':>14} "
          f"{'max |diff|':>11}")
    for r in res["offline"]:
        ref = f"{r['reference_s']:.3f}" if "reference_s" in r else "-"
        diff = f"{r['max_abs_diff']:.1e}" if "max_abs_diff" in r else "-"
        print(f"{r['frames']:>7} {r['ours_s'] * 1e3:>9.2f} {r['ours_solve_only_s'] * 1e3:>9.2f} {ref:>15} "
              f"{r['seol_matlab_s']:>14.2f} {diff:>11}")
    e = res["edit"]
    print(f"edit re-solve on a 1000-frame take (54x50): 12-frame range {e['range12_s'] * 1e3:.3f} ms, whole take "
          f"{e['whole_s'] * 1e3:.2f} ms ({e['range12_with_targets_s'] * 1e3:.2f} / "
          f"{e['whole_with_targets_s'] * 1e3:.2f} ms when the source targets are passed again); "
          f"solving the take from scratch {e['full_resolve_s'] * 1e3:.2f} ms")
    for k, v in res["streaming_72x150"].items():
        print(f"streaming 72 markers x 150 shapes {k}, {v['frames']} frames: p50 {v['p50_us']:.1f} us  "
              f"p99 {v['p99_us']:.1f} us (goal {v['goal_p99_us']:.0f}; thread CPU p50 {v['cpu_p50_us']:.1f}  "
              f"p99 {v['cpu_p99_us']:.1f}); pinv baseline p50 {v['baseline_pinv_p50_us']:.1f}  "
              f"p99 {v['baseline_pinv_p99_us']:.1f} us -> x{v['ratio_p50']:.1f} / x{v['ratio_p99']:.1f}; "
              f"load {v['load_avg']:.1f}")
    d = res["limits_drift"]
    print(f"stream of {d['stream_seconds']:.0f} s (54x50, K24 L4): clipping to limits costs "
          f"{d['clip_extra_percent']:+.2f}% velocity error; weight RMSE first minute "
          f"{d['weight_rmse_first_minute']:.4f}, last minute {d['weight_rmse_last_minute']:.4f}")
    return res


if __name__ == "__main__":
    sys.exit(suite_main(run, __doc__))
