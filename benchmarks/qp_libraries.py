"""Which QP library solves the per-frame bounded fit fastest, and how exactly (Curio et al. 2006 §2.3).

Every frame of the per-frame mode is the same box-constrained QP with a constant Hessian,

    minimise 1/2 w'Hw + f'w   s.t.  lower <= w <= upper,   H = B'B + lam I,  f = -B's,

so the contenders are used the way a stream would use them: whatever can be prepared once is
(factorisations, workspaces), and the previous frame's solution / active set warm-starts the next
where the library allows it. Accuracy is the max |w - w_ref| against scipy's BVLS at tight
tolerance. Problems: synthetic facial bases and takes (benchmarks/synthetic.py) at 54 markers x 50
shapes (Seol et al. 2012's size) and 72 x 150.

Run: ``python -m benchmarks.qp_libraries [--quick] [--json out.json]``.
"""

from __future__ import annotations

import os
import platform
import sys
import time

import numpy as np
from scipy.optimize import lsq_linear

from benchmarks.synthetic import frame_problems
from benchmarks.timing import suite_main

SIZES = [(54, 50), (72, 150)]
RIDGE = 1e-2


class ScipyBVLS:
    name, warm = "scipy lsq_linear bvls", None  # None: too slow for every frame

    def __init__(self, B, lo, hi, lam):
        self.A = np.vstack([B, np.sqrt(lam) * np.eye(B.shape[1])])
        self.pad = np.zeros(B.shape[1])
        self.lo, self.hi = lo, hi

    def step(self, s):
        return lsq_linear(self.A, np.concatenate([s, self.pad]), bounds=(self.lo, self.hi), method="bvls").x


class Quadprog:
    """Goldfarb-Idnani dual active set; takes R^-1 of H = R'R, so the factorisation is done once."""

    name, warm = "quadprog (R^-1 prefactored)", False

    def __init__(self, B, lo, hi, lam):
        import quadprog

        self.solve_qp = quadprog.solve_qp
        m = B.shape[1]
        H = B.T @ B + lam * np.eye(m)
        R = np.linalg.cholesky(H).T
        self.Rinv = np.linalg.inv(R)
        self.Bt = B.T.copy()
        self.C = np.hstack([np.eye(m), -np.eye(m)])
        self.b = np.concatenate([lo, -hi])

    def step(self, s):
        return self.solve_qp(self.Rinv, self.Bt @ s, self.C, self.b, 0, True)[0]


class DaqpCold:
    name, warm = "daqp.solve (setup per frame)", False

    def __init__(self, B, lo, hi, lam):
        import daqp

        self.solve = daqp.solve
        self.H = B.T @ B + lam * np.eye(B.shape[1])
        self.Bt, self.lo, self.hi = B.T.copy(), lo, hi
        self.A = np.zeros((0, B.shape[1]))

    def step(self, s):
        return self.solve(self.H, -(self.Bt @ s), self.A, self.hi, self.lo)[0]


class DaqpModel:
    """One workspace (H factored once); per frame only f changes; the active set carries over."""

    name, warm = "daqp.Model (prefactored, warm)", True

    def __init__(self, B, lo, hi, lam, warm: bool = True):
        import daqp

        m = B.shape[1]
        self.Bt = B.T.copy()
        self.model = daqp.Model()
        self.model.setup(B.T @ B + lam * np.eye(m), np.zeros(m), np.zeros((0, m)), hi.copy(), lo.copy())
        self.cold_sense = None if warm else np.zeros(m, dtype=np.int32)
        if not warm:
            self.name, self.warm = "daqp.Model (prefactored, cold)", False

    def step(self, s):
        if self.cold_sense is None:
            self.model.update(f=-(self.Bt @ s))
        else:
            self.model.update(f=-(self.Bt @ s), sense=self.cold_sense)
        return self.model.solve()[0]


class Proxsuite:
    """ProxQP with box constraints. Its WARM_START_WITH_PREVIOUS_RESULT segfaults (proxsuite 0.8.0)
    when set before the first solve, so the first solve is cold and warm starting is switched on after."""

    name, warm = "proxsuite proxqp dense box (warm)", True

    def __init__(self, B, lo, hi, lam):
        from proxsuite import proxqp

        m = B.shape[1]
        self.Bt = B.T.copy()
        self.qp = proxqp.dense.QP(m, 0, 0, True)
        self.qp.settings.eps_abs = 1e-9
        self.qp.settings.eps_rel = 0.0
        self.qp.init(B.T @ B + lam * np.eye(m), np.zeros(m), None, None, None, None, None, lo, hi)
        self.qp.solve()
        self.qp.settings.initial_guess = proxqp.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT

    def step(self, s):
        self.qp.update(g=-(self.Bt @ s))
        self.qp.solve()
        return self.qp.results.x.copy()


class Osqp:
    name, warm = "osqp (warm, polished)", True

    def __init__(self, B, lo, hi, lam):
        import osqp
        from scipy import sparse

        m = B.shape[1]
        self.Bt = B.T.copy()
        self.qp = osqp.OSQP()
        self.qp.setup(sparse.csc_matrix(np.triu(B.T @ B + lam * np.eye(m))), np.zeros(m),
                      sparse.identity(m, format="csc"), lo, hi, verbose=False, eps_abs=1e-7, eps_rel=1e-7,
                      polishing=True, warm_starting=True, max_iter=20000)

    def step(self, s):
        self.qp.update(q=-(self.Bt @ s))
        return self.qp.solve().x


def _livecap_qp(B, lo, hi, lam):
    """The project's own per-frame mode on top of the chosen library, to show its overhead."""
    from solvers.qp import FrameQP

    solver = FrameQP(B.reshape(-1, B.shape[1]), lo, hi, ridge=lam)
    valid = np.ones(B.shape[0] // 3, dtype=bool)

    class Wrapped:
        name, warm = "livecap FrameQP.step (daqp)", True

        def step(self, s):
            return solver.step(s.reshape(-1, 3), valid)

    return Wrapped()


CONTENDERS = [ScipyBVLS, Quadprog, DaqpCold, lambda *a: DaqpModel(*a, warm=False), DaqpModel, Proxsuite, Osqp,
              _livecap_qp]


def run(quick: bool = False) -> dict:
    """Per-frame p50/p99 (microseconds) and max error for each library at each size.

    Every contender steps through the whole take (so warm starts see real frame-to-frame
    changes); BVLS at tight tolerance is the reference on every ``check``-th frame (it is slow:
    seconds per frame at 72 x 150) and is timed on those frames alone; other cold solvers on every 4th.
    """
    frames = 240 if quick else 1200
    check = 24 if quick else 60
    results: dict = {"machine": f"{platform.machine()} {platform.python_implementation()} "
                                f"{platform.python_version()}, {os.cpu_count()} cpus, "
                                f"load {os.getloadavg()[0]:.1f}",
                     "frames": frames, "ridge": RIDGE, "sizes": {}}
    for n, m in SIZES:
        B, S, _ = frame_problems(n, m, frames, seed=n * 1000 + m)
        lo, hi = np.zeros(m), np.ones(m)
        checked = np.arange(0, frames, check)
        A = np.vstack([B, np.sqrt(RIDGE) * np.eye(m)])
        ref = {int(i): lsq_linear(A, np.concatenate([S[i], np.zeros(m)]), bounds=(lo, hi), method="bvls",
                                  tol=1e-14).x for i in checked}
        active = float(np.mean([(r <= lo + 1e-9) | (r >= hi - 1e-9) for r in ref.values()]))
        rows = {}
        for make in CONTENDERS:
            try:
                solver = make(B, lo, hi, RIDGE)
            except ImportError as exc:
                rows[getattr(make, "name", str(make))] = {"error": str(exc)}
                continue
            indices = checked if solver.warm is None else range(0, frames, 1 if solver.warm else 4)
            times, err = [], 0.0
            for i in indices:
                t0 = time.perf_counter_ns()
                w = solver.step(S[i])
                times.append((time.perf_counter_ns() - t0) / 1e3)
                if i in ref:
                    err = max(err, float(np.max(np.abs(w - ref[i]))))
            times = np.array(times[1:])  # the first call pays for allocation and a cold active set
            rows[solver.name] = {"p50_us": float(np.percentile(times, 50)), "p99_us": float(np.percentile(times, 99)),
                                 "max_err": err, "warm": bool(solver.warm)}
        results["sizes"][f"{n}x{m}"] = {"active_bound_fraction": active, "libraries": rows}
    print_table(results)
    return results


def print_table(results: dict) -> None:
    print(f"per-frame bounded QP, {results['frames']} frames, ridge {results['ridge']}, on {results['machine']}")
    for size, block in results["sizes"].items():
        print(f"\n{size} (markers x shapes), {block['active_bound_fraction'] * 100:.0f}% of weights on a bound")
        print(f"  {'library':38s} {'p50 us':>9s} {'p99 us':>9s} {'max |w-ref|':>12s}")
        for name, r in block["libraries"].items():
            if "error" in r:
                print(f"  {name:38s} unavailable: {r['error']}")
                continue
            print(f"  {name:38s} {r['p50_us']:9.1f} {r['p99_us']:9.1f} {r['max_err']:12.2e}")


if __name__ == "__main__":
    sys.exit(suite_main(run, __doc__))
