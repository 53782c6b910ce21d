"""``livecap review``'s interactive math: drag solves, spacetime edits over 100 frames, key reduction.

    python -m benchmarks.review [--quick]

- Drag (direct manipulation, solvers/manipulation.py) at 60 markers x 53 shapes (synthetic, shaped like a
  face) with 1, 3 and all 60 marker sites pinned, against scipy's BVLS on the same problem in the same run
  (time ratio and max weight difference). Goal: <= 5 ms.
- Spacetime edit over a 100-frame range on the demo take (2400 frames, 60 markers, 43 shapes): Seol's
  movement solve (what the review page uses) and the noise-robust solve's edit. Goal: <= 20 ms.
- Key reduction (solvers/keyreduce.py) of the demo take's solve at max error 0.01: keys as a fraction of
  samples, worst error. Goal: <= 15 % of frames as keys. Beside it, the LINEAR keys of keys-linear.glb
  (livecap/review/linear.py) as a fraction of frames, against the cubic union of keys.glb.
- The edit journal (livecap/review/journal.py): one edit's line appended and fsync'd, for 25- and
  101-frame edits, on the disk holding this checkout; beside the Seol edit's time above.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.optimize

from benchmarks.synthetic import synthetic_profile
from benchmarks.timing import suite_main, table, time_calls
from livecap.review.linear import linear_keys
from solvers.keyreduce import KeySettings, evaluate_keys, reduce_curves, shared_keys
from solvers.manipulation import DirectManipulation, ManipulationSettings
from solvers.movement import Edit


def drag(n_markers: int = 60, n_shapes: int = 53, pins: int = 3, count: int = 300, pull: float = 1.0) -> dict:
    prof = synthetic_profile(n_markers, n_shapes, seed=1)
    rng = np.random.default_rng(2)
    B = prof.basis.reshape(n_markers, 3, n_shapes)
    chosen = rng.choice(n_markers, pins, replace=False)
    deltas = np.transpose(B[chosen], (2, 0, 1))  # m x P x 3
    rest = prof.target_sites[chosen]
    prep0 = time.perf_counter()
    dm = DirectManipulation(rest, deltas, prof.lower, prof.upper, ManipulationSettings(pull=pull))
    prepare_ms = (time.perf_counter() - prep0) * 1e3
    cur = np.clip(rng.uniform(-0.3, 0.8, (count + 50, n_shapes)), 0, 1)
    goals = rest[None] + np.einsum("tm,mpk->tpk", np.clip(cur + rng.normal(0, 0.4, cur.shape), -0.3, 1.3), deltas)
    t = time_calls(lambda i: dm.step(goals[i], cur[i]), count, warmup=50)
    A = np.vstack([deltas.reshape(n_shapes, -1).T, np.sqrt(pull) * np.eye(n_shapes)])

    def bvls(i):
        b = np.concatenate([(goals[i] - rest).ravel(), np.sqrt(pull) * cur[i]])
        return scipy.optimize.lsq_linear(A, b, bounds=(prof.lower, prof.upper), method="bvls", tol=1e-12).x

    nref = min(count, 100)
    ref = time_calls(bvls, nref, warmup=5)
    diff = max(float(np.max(np.abs(dm.step(goals[i], cur[i]) - bvls(i)))) for i in range(nref))
    active = float(np.mean([np.any((w <= 0) | (w >= 1)) for w in (dm.step(goals[i], cur[i]) for i in range(nref))]))
    return {"size": f"{n_markers}x{n_shapes}", "pins": pins, "prepare_ms": prepare_ms,
            "median_ms": t["median_us"] / 1e3, "p99_ms": t["p99_us"] / 1e3, "bvls_median_ms": ref["median_us"] / 1e3,
            "speedup": ref["median_us"] / t["median_us"], "max_diff_vs_bvls": diff, "frames_with_bounds": active}


def edits(quick: bool) -> tuple[list[dict], object]:
    from benchmarks.demo_take import demo_take
    from livecap.modes.movement import build_movement
    from livecap.modes.registry import build_solver

    demo = demo_take()
    W = build_solver("movement", demo.profile, {}).solve(demo.targets, demo.valid)
    rows = []
    rng = np.random.default_rng(4)
    j = demo.profile.names.index("jawOpen")
    for label, opts, n in (("seol (review)", {"robust": False}, 10 if quick else 40),
                           ("noise-robust", {}, 2 if quick else 5)):
        editor = build_movement(demo.profile, opts)
        times = []
        for _ in range(n + 1):
            k = int(rng.integers(100, len(W) - 100))
            a, b = k - 50, k + 49
            pad = 32 if hasattr(editor, "smooth") else 0  # as livecap.review.session.ReviewSession.edit
            lo, hi = a - pad, b + 1 + pad
            t0 = time.perf_counter()
            E = editor.edit(W[lo:hi].copy(), [Edit(k - lo, {j: 0.9}, (a - lo, b - lo))], demo.targets[lo:hi],
                            demo.valid[lo:hi])
            times.append(time.perf_counter() - t0)
            assert abs(E[k - lo, j] - 0.9) < 1e-9
        t = np.array(times[1:]) * 1e3
        rows.append({"editor": label, "range": 100, "edits": n, "median_ms": float(np.median(t)),
                     "max_ms": float(t.max())})
    return rows, (demo, W)


def keys(demo, W_movement, tol: float = 0.01) -> list[dict]:
    from livecap.modes.registry import build_solver

    times = np.arange(len(W_movement)) / 120.0
    rows = []
    qp = build_solver("qp", demo.profile, {})
    W_qp = (qp.solve(demo.targets, demo.valid) if hasattr(qp, "solve")
            else np.array([qp.step(demo.targets[i], demo.valid[i]) for i in range(len(times))]))
    curves = {"movement (review default)": W_movement, "qp (per-frame, noisy)": W_qp}
    for label, W in curves.items():
        t0 = time.perf_counter()
        ks = reduce_curves(times, W, KeySettings(tol))
        sec = time.perf_counter() - t0
        worst = max(float(np.max(np.abs(evaluate_keys(k, times) - W[:, j]))) for j, k in enumerate(ks))
        per_shape = np.array([len(k.frames) for k in ks]) / len(times)
        frames, *_ = shared_keys(ks, times)
        linear = linear_keys(times, W, tol)
        rows.append({"curves": label, "max_error": tol, "keys": int(sum(len(k.frames) for k in ks)),
                     "mean_frac": float(per_shape.mean()), "max_shape_frac": float(per_shape.max()),
                     "glTF_frac": len(frames) / len(times), "linear_glTF_frac": len(linear) / len(times),
                     "worst": worst, "seconds": sec})
    return rows


def journal(count: int = 40) -> list[dict]:
    import tempfile
    from pathlib import Path

    from livecap.review.journal import EditJournal

    rng = np.random.default_rng(5)
    rows = []
    with tempfile.TemporaryDirectory(dir=Path(__file__).parent) as folder:  # this checkout's disk, not a tmpfs
        for n in (25, 101):
            j = EditJournal(Path(folder) / f"take{n}.review-edits", "bench")
            times = []
            for i in range(count):
                after = rng.uniform(0, 1, (n, 43)).tolist()
                t0 = time.perf_counter()
                j.append({"op": "edit", "id": i + 1, "client": "bench", "a": 0, "b": n - 1, "after": after})
                times.append(time.perf_counter() - t0)
            j.close()
            t = np.array(times) * 1e3
            rows.append({"frames": n, "shapes": 43, "appends": count, "line_kB": j.path.stat().st_size / count / 1024,
                         "median_ms": float(np.median(t)), "max_ms": float(t.max())})
    return rows


def run(quick: bool = False) -> dict:
    n = 100 if quick else 1000
    drags = [drag(pins=p, count=n) for p in (1, 3, 60)]
    print(table(drags, ["size", "pins", "prepare_ms", "median_ms", "p99_ms", "bvls_median_ms", "speedup",
                        "max_diff_vs_bvls", "frames_with_bounds"], "drag solve (goal <= 5 ms)"))
    edit_rows, (demo, W) = edits(quick)
    print(table(edit_rows, ["editor", "range", "edits", "median_ms", "max_ms"],
                "\nspacetime edit, demo take (goal <= 20 ms for 100 frames)"))
    key_rows = keys(demo, W)
    print(table(key_rows, ["curves", "max_error", "keys", "mean_frac", "max_shape_frac", "glTF_frac",
                           "linear_glTF_frac", "worst", "seconds"],
                "\nkey reduction, demo take (goal <= 15 % of frames as keys)"))
    journal_rows = journal(10 if quick else 40)
    print(table(journal_rows, ["frames", "shapes", "appends", "line_kB", "median_ms", "max_ms"],
                "\nedit journal: one edit appended and fsync'd"))
    return {"drag": drags, "edit": edit_rows, "keys": key_rows, "journal": journal_rows}


if __name__ == "__main__":
    raise SystemExit(suite_main(run, __doc__))
