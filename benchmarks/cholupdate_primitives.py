"""k rank-1 up/downdates of a 216 x 216 Cholesky factor (solvers.cholupdate_kernels) against the refactor
solvers.marker_space_qp does for k changed columns (dsyrk on S's lower triangle + dpotrf), 72 x 1000's sizes
(r = 216, ~500 columns free). Median wall µs of 30, one BLAS thread."""

from __future__ import annotations

import json
import os
import sys
import time

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
from scipy.linalg.blas import dsyrk  # noqa: E402
from scipy.linalg.lapack import dpotrf  # noqa: E402

from solvers.cholupdate_kernels import lowrank_update  # noqa: E402


def _median_us(f, n: int = 30) -> float:
    t = []
    for _ in range(n):
        t0 = time.perf_counter()
        f()
        t.append(time.perf_counter() - t0)
    return float(np.median(t) * 1e6)


def main(out: str | None = None) -> dict:
    rng = np.random.default_rng(0)
    r = 216
    W = rng.standard_normal((r, 1006)) * 0.3
    S = np.asfortranarray(np.eye(r) + W[:, :500] @ W[:, :500].T)
    L0 = np.asfortranarray(np.linalg.cholesky(S))
    lowrank_update(L0.copy(order="F"), np.asfortranarray(W[:, 500:501]), np.ones(1))  # compile / load
    rows = {}
    for k in (1, 4, 8, 12, 16, 24, 32, 48, 66):
        X = np.asfortranarray(W[:, 500:500 + k])
        sign = np.ones(k)

        def refactor(X=X):
            dpotrf(dsyrk(1.0, X, beta=1.0, c=S.copy(order="F"), lower=1, overwrite_c=1), lower=1, clean=0)

        def updates(X=X, s=sign):
            lowrank_update(L0.copy(order="F"), X.copy(order="F"), s)

        rows[k] = {"rank-1 updates": _median_us(updates),
                   "dsyrk + dpotrf": _median_us(refactor)}
        print(k, {a: round(b) for a, b in rows[k].items()})
    res = {"utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()), "load": os.getloadavg(), "r": r, "rows": rows}
    if out:
        with open(out, "w") as fh:
            json.dump(res, fh, indent=1)
    return res


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else None)
