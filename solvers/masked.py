"""Movement matching with the rows of missing markers dropped (the exact masked objective).

A marker missing at frame t removes its rows from the position term at t and from the two
movement terms (t-1, t) and (t, t+1). The blocks then vary per frame, so the decoupling of
:mod:`solvers.blocks` no longer applies; the system stays block-tridiagonal and is solved by a
block Thomas sweep over the free frames, O(T m^3). Blocks are computed once per distinct
visibility pattern (most pairs of frames see every marker). Used by
``MovementMatching(missing="exact")`` and as the check on the default gap filling.
"""

from __future__ import annotations

import numpy as np

from solvers.blocks import IllPosedError, MovementBlocks


def _blocks_for(masks: np.ndarray, B: np.ndarray, row_weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """B^T diag(rows) B for each distinct marker mask; returns (blocks, index per mask)."""
    uniq, inv = np.unique(masks, axis=0, return_inverse=True)
    out = np.empty((len(uniq), B.shape[1], B.shape[1]))
    for i, mk in enumerate(uniq):
        rows = np.repeat(mk, 3)
        Bm = B[rows]
        out[i] = Bm.T @ (row_weights[rows][:, None] * Bm)
    return out, inv.reshape(-1)


def solve_masked(blocks: MovementBlocks, targets: np.ndarray, valid: np.ndarray, W: np.ndarray,
                 isfree: np.ndarray) -> np.ndarray:
    """Weights for the free frames of ``W`` (T x m; fixed frames already set) under the masked objective."""
    B = blocks.basis
    T, m = W.shape
    S = np.where(valid[..., None], targets, 0.0).reshape(T, -1)
    ones = np.ones(B.shape[0])
    pair = valid[1:] & valid[:-1]  # pair p links frames p and p+1
    Gp, gi = _blocks_for(pair, B, ones)
    rows_p = np.repeat(pair, 3, axis=1)
    dS = np.where(rows_p, S[1:] - S[:-1], 0.0)  # masked velocity per pair
    BdS = dS @ B  # B^T d_p for each pair, (T-1) x m
    Kc = blocks.ridge * np.eye(m)
    const = np.zeros(m)
    if blocks.prior is not None:
        Kc = Kc + blocks.alpha * blocks.prior.precision
        const = blocks.alpha * blocks.prior.gradient_constant()
    if blocks.beta > 0:
        Hf, hi = _blocks_for(valid, B, blocks.row_weights)
        BMs = (S * blocks.row_weights) @ B * blocks.beta  # beta B^T M^2 s_t (missing rows are 0 in S)
    free = np.flatnonzero(isfree)
    N = len(free)
    if N == 0:
        return W

    def diag_block(t: int) -> tuple[np.ndarray, np.ndarray]:
        D = Kc.copy()
        r = const.copy()
        if t > 0:
            D += Gp[gi[t - 1]]
            r += BdS[t - 1]
            if not isfree[t - 1]:
                r += Gp[gi[t - 1]] @ W[t - 1]
        if t < T - 1:
            D += Gp[gi[t]]
            r -= BdS[t]
            if not isfree[t + 1]:
                r += Gp[gi[t]] @ W[t + 1]
        if blocks.beta > 0:
            D += blocks.beta * Hf[hi[t]]
            r += BMs[t]
        return D, r

    Z = np.zeros((N, m, m))  # D'^-1 C_i (coupling to the next free frame)
    z = np.zeros((N, m))
    prevC = None
    for i, t in enumerate(free):
        D, r = diag_block(t)
        if prevC is not None:
            D = D - prevC.T @ Z[i - 1]
            r = r - prevC.T @ z[i - 1]
        nxt = i + 1 < N and free[i + 1] == t + 1
        C = -Gp[gi[t]] if nxt else None
        rhs = r[:, None] if C is None else np.column_stack([C, r])
        try:
            X = np.linalg.solve(D, rhs)
        except np.linalg.LinAlgError:
            raise IllPosedError(f"masked movement matching is singular at frame {t} (too few visible markers "
                                "and no boundary, prior, beta or ridge)") from None
        z[i] = X[:, -1]
        if C is not None:
            Z[i] = X[:, :-1]
        prevC = C
    x = np.zeros((N, m))
    x[-1] = z[-1]
    for i in range(N - 2, -1, -1):
        x[i] = z[i] - (Z[i] @ x[i + 1] if free[i + 1] == free[i] + 1 else 0.0)
    W = W.copy()
    W[free] = x
    return W
