"""Literal sparse implementation of Seol et al. 2012 Eq. 5 (the baseline for tests and benchmarks).

Everything is written exactly as in the paper, with vec(W) stacking the columns of the m x f
weight matrix (frame-major) and scipy.sparse Kronecker products:

    E_match = |(D (x) B) vec(W) - (D (x) I) vec(S)|^2                        (Eq. 5)
    E_prior = v^T (I_f (x) Lambda^-1) v,  v = (I_f (x) E^T B) vec(W) - 1 (x) E^T mean   (§5)
    E_pos   = |(I_f (x) M B) vec(W) - (I_f (x) M) vec(S)|^2                  (§7.1)

The known (boundary) entries of vec(W) move to the right-hand side (appendix) and the normal
equations are solved with a sparse direct solver. Rows of missing markers can be dropped
(``valid``), which gives the exact masked objective. Deliberately unoptimised: it forms
(f-1)3n x fm sparse matrices with 2(f-1)3nm entries.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from solvers.prior import PCAPrior


def difference_matrix(f: int) -> sp.csr_matrix:
    """The backward first difference D ((f-1) x f) of Seol's appendix."""
    return sp.diags([-np.ones(f - 1), np.ones(f - 1)], [0, 1], shape=(f - 1, f), format="csr")


def solve_reference(basis: np.ndarray, targets: np.ndarray, fixed: Mapping[int, np.ndarray], *,
                    alpha: float = 0.0, prior: PCAPrior | None = None, beta: float = 0.0,
                    marker_weights: np.ndarray | None = None, ridge: float = 0.0,
                    valid: np.ndarray | None = None) -> np.ndarray:
    """Weights (f x m) minimising Eq. 4/5 (+ beta position + ridge) with ``fixed`` frames known."""
    N, rhs, known, x = reference_system(basis, targets, fixed, alpha=alpha, prior=prior, beta=beta,
                                        marker_weights=marker_weights, ridge=ridge, valid=valid)
    x[~known] = spla.spsolve(N, rhs)
    return x.reshape(len(x) // np.asarray(basis).shape[1], -1)


def reference_system(basis: np.ndarray, targets: np.ndarray, fixed: Mapping[int, np.ndarray], *,
                     alpha: float = 0.0, prior: PCAPrior | None = None, beta: float = 0.0,
                     marker_weights: np.ndarray | None = None, ridge: float = 0.0,
                     valid: np.ndarray | None = None) -> tuple[sp.csc_matrix, np.ndarray, np.ndarray, np.ndarray]:
    """The literal normal equations over the unknown entries of vec(W): (N, rhs, known, x).

    The objective is x_u^T N x_u - 2 rhs^T x_u + const over the unknowns x_u = x[~known];
    ``x`` holds the fixed frames' values (frame-major, f*m). Tests hand it to QP solvers."""
    B = np.asarray(basis, dtype=np.float64)
    n3, m = B.shape
    S = np.asarray(targets, dtype=np.float64).reshape(len(targets), -1)
    f = len(S)
    vecS = S.reshape(-1)  # columns of the 3n x f matrix S stacked
    D = difference_matrix(f)
    Bs = sp.csr_matrix(B)
    blocks_A, blocks_b = [], []
    A = sp.kron(D, Bs, format="csr")
    b = sp.kron(D, sp.identity(n3), format="csr") @ vecS
    if valid is not None:
        rows = np.repeat(np.asarray(valid, dtype=bool), 3, axis=1)  # f x 3n
        keep = (rows[1:] & rows[:-1]).reshape(-1)
        A, b = A[keep], b[keep]
    blocks_A.append(A)
    blocks_b.append(b)
    if alpha > 0:
        if prior is None:
            raise ValueError("alpha > 0 needs a prior")
        scale = 1.0 / np.sqrt(prior.eigenvalues)
        EtB = prior.eigenvectors.T @ B  # v = E^T (B w - mean) = E^T B (w - w_mean)
        blocks_A.append(np.sqrt(alpha) * sp.kron(sp.identity(f), sp.csr_matrix(scale[:, None] * EtB), format="csr"))
        blocks_b.append(np.sqrt(alpha) * np.tile(scale * (EtB @ prior.mean_weights), f))
    if beta > 0:
        mw = np.ones(n3 // 3) if marker_weights is None else np.asarray(marker_weights, dtype=np.float64)
        Mrow = sp.diags(np.repeat(mw, 3))
        A = np.sqrt(beta) * sp.kron(sp.identity(f), sp.csr_matrix(Mrow @ B), format="csr")
        b = np.sqrt(beta) * (sp.kron(sp.identity(f), Mrow, format="csr") @ vecS)
        if valid is not None:
            keep = np.repeat(np.asarray(valid, dtype=bool), 3, axis=1).reshape(-1)
            A, b = A[keep], b[keep]
        blocks_A.append(A)
        blocks_b.append(b)
    if ridge > 0:
        blocks_A.append(np.sqrt(ridge) * sp.identity(f * m, format="csr"))
        blocks_b.append(np.zeros(f * m))
    A = sp.vstack(blocks_A, format="csc")
    b = np.concatenate(blocks_b)
    known = np.zeros(f * m, dtype=bool)
    x = np.zeros(f * m)
    for frame, w in fixed.items():
        fr = int(frame) % f
        known[fr * m:(fr + 1) * m] = True
        x[fr * m:(fr + 1) * m] = np.asarray(w, dtype=np.float64)
    A1, A2 = A[:, ~known], A[:, known]
    R = b - A2 @ x[known]  # appendix: the known rows of W^T moved to the right-hand side
    return (A1.T @ A1).tocsc(), A1.T @ R, known, x
