"""Checking an animation prior against the actor: its mean re-centred where the frames say the actor rests
elsewhere (issue 41.2); its variance widened only on request.

A prior learned from other performers can hold a direction tight that this actor moves along
(issue 41: the prior held eyeLookUp at 0, so eyeWide took its motion, +0.38). Held-out *markers*
cannot catch it: the markers see that direction weakly (eyeWide / eyeLookUp, cosine 0.94). The
*frames* can: over time the actor's markers vary along B u_k more than the prior's variance
lambda_k of direction u_k allows. So each principal direction's variance v_k is chosen by the
marginal likelihood of the frames (type-II maximum likelihood, the evidence: Bishop 2006 §3.5;
MacKay 1992's fixed-point updates with the effective number of parameters gamma):

    w_t ~ N(mu, U diag(v) U^T),  x_t = B w_t + P p_t + e_t,  e_t ~ N(0, s2 I)

with ``P`` the unbounded head-pose columns (solvers.pose_refine, a broad fixed variance) and the
noise ``s2`` estimated with the v_k. Each frame uses its own visible markers. v_k may only grow
(v_k >= lambda_k): a prior from other performers is widened where the actor leaves it and kept where
the data says nothing, so it can only move towards the data. Ignored: the weights' limits and the
frames' correlation in time (each frame counts as an independent draw).

The variance alone cannot catch an actor who *rests* elsewhere than the prior's performers (issue 41.2: S88-001
squints all take, eyeSquint ~0.48 against the prior's 0.17, sd 0.08; the markers barely tell eyeSquint from
eyeLookUp, so the prior's mean decides). So the mean is chosen by the same evidence too (type-II ML of the mean,
Bishop 2006 §3.5, here its posterior): the prior's own distribution N(mu, cov) is the hyperprior of this actor's
mean (a new performer's mean lies about as far from the others' as one of their frames), and the frames'
marginal likelihood moves it. Given the variances it is quadratic in the mean, one Newton step per iteration.
Where the frames see a direction well the mean goes to the actor's; where they see it weakly it stays near the
prior's: no threshold. The frames of a take are not independent draws: each direction's evidence for the mean
counts only its effective number of frames (an AR(1) reading of its lag-one autocorrelation), else a second of
acting re-centres the prior on that second (measured: apfel and MySlate worse than no prior). Kept inside the
weights' box.

What the check returns (measured, docs/robustness.md "The prior's mean re-centred" and "A prior that carries its
mean's uncertainty", 12 leave-one-performer-out cases): the re-centred mean, and for a frame of this actor the
posterior predictive N(mean, cov + the mean's posterior covariance) (Bishop 2006 §3.3.2): the prior's *own* spread
where the frames pin its mean, up to twice it where they do not (never worse than no prior 8 -> 10 of 12 streamed,
11 -> 12 of 12 offline, with the streamed changes beside it). The variances are still estimated (the mean's
evidence needs them), but widening the prior where they exceed 10 x its own (the check before, a threshold set on
the judged files) cost more than it saved: with it, 10 / 9 of 12 cases never worse than no prior (streamed /
offline), without it 11 / 11.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

POSE_VARIANCE = 1e2  # mm^2: the pose columns' prior, broad (the stabiliser's residual is ~1 mm)


@dataclass(frozen=True)
class Support:
    axes: np.ndarray  # m x m, the prior's principal directions (columns)
    before: np.ndarray  # m, the prior's variance per direction
    after: np.ndarray  # m, the variance the frames' marginal likelihood chose where > ``outside`` x before, else before
    noise_var: float  # mm^2, the noise the fit estimated with them
    iterations: int
    mean: np.ndarray  # m, the actor's mean the frames' evidence chose (the prior's where they say nothing)
    mean_cov: np.ndarray | None = None  # m x m, that mean's posterior covariance in the axes' coordinates

    @property
    def cov(self) -> np.ndarray:
        """The prior for this actor's next frame: its spread about its mean, plus what is not known of that mean."""
        inner = np.diag(self.after) if self.mean_cov is None else np.diag(self.after) + self.mean_cov
        return self.axes @ inner @ self.axes.T

    @property
    def precision(self) -> np.ndarray:
        if self.mean_cov is None:
            return (self.axes / self.after) @ self.axes.T
        return self.axes @ np.linalg.inv(np.diag(self.after) + self.mean_cov) @ self.axes.T

    @property
    def widened(self) -> np.ndarray:
        """Indices of the directions widened."""
        return np.flatnonzero(self.after > self.before)

    def added_per_shape(self) -> np.ndarray:
        """Variance added to each shape's weight (the diagonal of the widening)."""
        return ((self.axes**2) * (self.after - self.before)).sum(1)


def widen_prior(basis: np.ndarray, mean: np.ndarray, cov: np.ndarray, targets: np.ndarray, valid: np.ndarray,
                lower: np.ndarray, upper: np.ndarray, extra: np.ndarray | None = None, noise_var: float = 0.25,
                iterations: int = 30, tol: float = 1e-2, outside: float = np.inf, recentre: bool = True) -> Support:
    """The prior ``(mean, cov)`` over the m weights of ``basis`` (3n x m) widened per principal direction by the
    marginal likelihood of ``targets`` (T x 3n marker displacements, ``valid`` T x n). ``extra``: unbounded columns
    fitted beside the basis (the head pose), with a broad fixed prior. ``noise_var``: where the noise estimate
    starts (mm^2). ``outside``: a direction keeps the prior's variance unless the frames' choice exceeds it this
    many times (the check before branch prior3 used 10; by default never, see the module's docstring).
    A direction's variance is capped at what the weights' box allows. ``recentre``: the mean chosen by the
    frames' evidence too (the module's docstring), else kept. Iterates until no variance moves by more than
    ``tol`` (relative) and the mean by more than ``tol`` of the prior's sd.

    Each iteration inverts the all-seen k x k matrix once and takes each frame's hidden markers out of it by
    Woodbury (Golub & Van Loan 2013 §2.1.4): a frame's C_t = (A - U'U / s2)^-1 = C + W'(s2 I - W U')^-1 W, W = U C,
    with U its hidden rows, a 3h x 3h system for h hidden markers instead of a k x k inverse per frame (issue 39
    item 2: the 60 frames of a 30 s ICT take's check, 59 columns, ~3 hidden markers a frame: 45 -> ~8 ms)."""
    B = np.asarray(basis, float)
    mu0 = np.asarray(mean, float)
    n3, m = B.shape
    lam, U = np.linalg.eigh(np.asarray(cov, float))
    lam = np.maximum(lam, 1e-12)
    E = np.zeros((n3, 0)) if extra is None else np.asarray(extra, float)
    D = np.hstack([B @ U, E])  # rotated design: direction coordinates, then the extra columns
    k = D.shape[1]
    ok = np.asarray(valid, bool)
    X = np.asarray(targets, float).reshape(len(ok), n3) - B @ mu0
    rows = np.repeat(ok, 3, axis=1)
    X = np.where(rows, X, 0.0)
    keep = ok.sum(1) >= 3
    X, rows, ok = X[keep], rows[keep], ok[keep]
    half = (np.abs(U).T @ (np.asarray(upper, float) - np.asarray(lower, float))) / 2
    cap = np.maximum(half**2, lam)
    if not len(X):
        return Support(U, lam, lam.copy(), float(noise_var), 0, mu0.copy())
    G = D.T @ D
    hidden = hidden_rows(D, ok)
    b = X @ D  # T x k (invalid rows are 0)
    c = (X**2).sum(1)
    count = rows.sum(1).astype(float)
    v = np.r_[lam, np.full(k - m, POSE_VARIANCE)]
    s2 = float(noise_var)
    a = np.zeros(m)  # the mean's offset from the prior's, in the prior's directions
    done = 0
    while done < iterations:
        done += 1
        Cb, diag, Csum = _frame_inverses(G / s2 + np.diag(1.0 / v), hidden, s2, b)
        y = Cb / s2
        gamma = 1.0 - diag / v  # per frame and direction: how much the data determines it
        g = np.maximum(gamma[:, :m].sum(0), 1e-12)
        new = np.clip((y[:, :m] ** 2).sum(0) / g, lam, cap)
        resid = c - 2 * (y * b).sum(1) + _seen_quadratic(y, G, hidden)
        s2 = float(max(resid.sum() / max((count - gamma.sum(1)).sum(), 1.0), 1e-8))
        change = float(np.max(np.abs(np.log(new / v[:m]))))
        if recentre:
            # the log evidence's gradient in the mean is V^-1 y_t per frame, its curvature V^-1 - V^-1 C_t V^-1
            # (Woodbury), each direction's frames counted as the independent ones they are worth; the hyperprior
            # N(prior's mean, prior's cov) adds a / lam and 1 / lam
            f = np.sqrt(_independent_share(y[:, :m]))
            grad = f**2 * (y[:, :m].sum(0) / v[:m]) - a / lam
            H = f[:, None] * (len(y) * np.diag(1.0 / v) - Csum / np.outer(v, v))[:m, :m] * f + np.diag(1.0 / lam)
            target = np.clip(mu0 + U @ (a + np.linalg.solve(H, grad)), lower, upper)
            step = U.T @ (target - mu0) - a
            a = a + step
            shift = B @ (U @ step)
            X = np.where(rows, X - shift, 0.0)
            b = X @ D
            c = (X**2).sum(1)
            change = max(change, float(np.max(np.abs(step) / np.sqrt(lam))))
        v[:m] = new
        if change < tol:
            break
    mean_cov = np.linalg.inv(H) if recentre and done else None
    return Support(U, lam, np.where(v[:m] > outside * lam, v[:m], lam), s2, done, mu0 + U @ a, mean_cov)


def hidden_rows(D: np.ndarray, ok: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The frames grouped by how many markers they miss (h > 0): each group's frame indices and its frames' hidden
    rows of ``D`` (frames x 3h x k), for a Woodbury downdate per group (the prior check, the evidence, and
    solvers.prior_strength.take_strength's folds)."""
    out = []
    missing = ~ok
    h = missing.sum(1)
    for j in np.unique(h[h > 0]):
        sel = np.flatnonzero(h == j)
        idx = np.nonzero(missing[sel])[1].reshape(len(sel), j, 1)
        out.append((sel, D[(3 * idx + np.arange(3)).reshape(len(sel), 3 * j)]))
    return out


def _frame_inverses(A: np.ndarray, hidden: list, s2: float, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """With ``A`` every marker seen's matrix (k x k) and each frame's C_t = (A - U_t'U_t / s2)^-1 (U_t its hidden
    rows, ``hidden`` as :func:`hidden_rows`): per frame C_t b_t and C_t's diagonal (T x k), and the sum of the C_t."""
    C = np.linalg.inv(A)
    T, k = b.shape
    Cb, diag, Csum = b @ C, np.tile(np.diag(C), (T, 1)), T * C
    for sel, U in hidden:
        W = U @ C  # frames x 3h x k
        V = np.linalg.solve(s2 * np.eye(U.shape[1]) - W @ np.swapaxes(U, 1, 2), W)
        Cb[sel] += np.einsum("srk,sr->sk", V, np.einsum("srk,sk->sr", W, b[sel]))
        diag[sel] += (W * V).sum(1)
        Csum += W.reshape(-1, k).T @ V.reshape(-1, k)
    return Cb, diag, Csum


def _seen_quadratic(y: np.ndarray, G: np.ndarray, hidden: list) -> np.ndarray:
    """Per frame y_t' P_t'P_t y_t over its seen rows: ``G`` = every row's D'D, less the hidden rows'."""
    q = ((y @ G) * y).sum(1)
    for sel, U in hidden:
        q[sel] -= (np.einsum("srk,sk->sr", U, y[sel]) ** 2).sum(1)
    return q


def _independent_share(y: np.ndarray) -> np.ndarray:
    """Per column of ``y`` (frames in time order x directions): the share of its frames that count as independent
    for its mean, (1 - rho) / (1 + rho) with rho its lag-one autocorrelation (an AR(1) process's effective sample
    size): a second of acting at 60 Hz is worth a few frames, not 60."""
    d = y - y.mean(0)
    rho = (d[1:] * d[:-1]).sum(0) / np.maximum((d**2).sum(0), 1e-300)
    rho = np.clip(rho, 0.0, 1.0 - 1e-6)
    return (1 - rho) / (1 + rho)


def evidence_strength(basis: np.ndarray, mean: np.ndarray, precision: np.ndarray, grid: np.ndarray,
                      targets: np.ndarray, valid: np.ndarray, m: int, factors: dict | None = None) -> np.ndarray:
    """Log marginal likelihood of the frames per prior strength a in ``grid``, up to a constant (type-II ML, the
    evidence: Bishop 2006 §3.5): w ~ N(mean, s2 / a P^-1) on the first m columns of ``basis``, the rest (the head
    pose) flat, x_t = B w_t + e_t, e_t ~ N(0, s2 I) on each frame's visible markers, s2 at its maximum for each a.
    Frames with fewer than 3 markers seen are left out; each frame counts as an independent draw. Every frame's Hessian
    B_v'B_v + a P is the all-seen one less its hidden markers' rows: per frame the hidden rows' small downdate
    (Woodbury; the determinant lemma), a 3q x 3q system, not a k x k one (the check's 60 frames held 57 patterns on
    the ICT takes: 4.5x faster, issue 39). The all-seen Hessians of every strength from one factorisation: with
    B'B = LL' and L^-1 P L^-T = Q diag(d) Q', (B'B + aP)^-1 = M diag(1 / (1 + a d)) M' (M = L^-T Q) and
    log det(B'B + aP) = log det(B'B) + sum log(1 + a d) (the pair's generalised eigenproblem, Golub & Van Loan 2013
    §8.7; as solvers.prior_strength.take_strength; issue 39 item 2: a Cholesky solve per strength was ~2/3 of it).
    ``factors``: a dict that keeps (M, d, log det B'B) for the next call on the same basis and prior."""
    B = np.asarray(basis, float)
    n3, k = B.shape
    ok = np.asarray(valid, bool).reshape(len(valid), n3 // 3)
    Z = np.where(np.repeat(ok, 3, axis=1), np.asarray(targets, float).reshape(len(ok), n3) - B @ mean, 0.0)
    keep = ok.sum(1) >= 3
    Z, ok = Z[keep], ok[keep]
    c = (Z**2).sum(1)
    dof = 3 * ok.sum() - (k - m) * len(Z)
    logdet_p = np.linalg.slogdet(precision[:m, :m])[1]
    grid = np.asarray(grid, float)
    if factors is not None and "evidence" in factors:
        M, d, logdet_g = factors["evidence"]
    else:
        L = np.linalg.cholesky(B.T @ B)
        Li = np.linalg.solve(L, np.eye(k))
        d, Q = np.linalg.eigh(Li @ np.asarray(precision, float) @ Li.T)
        d = np.maximum(d, 0.0)
        M, logdet_g = Li.T @ Q, 2 * np.log(np.diag(L)).sum()
        if factors is not None:
            factors["evidence"] = M, d, logdet_g
    D = 1.0 / (1.0 + grid[:, None] * d)  # strengths x k: (B'B + aP)^-1 = M diag(D_a) M'
    BM = B @ M
    bm = Z @ BM  # frames x k: M'b_t
    quad = (bm**2).sum(0) @ D.T
    logdet = (logdet_g - np.log(D).sum(1)) * len(Z)
    for sel, Us in hidden_rows(BM, ok):  # the frames missing the same number of markers; their hidden rows, M'-wise
        UD = Us[None] * D[:, None, None, :]  # strengths x frames x 3j x k
        S = np.eye(Us.shape[1]) - UD @ np.swapaxes(Us, 1, 2)[None]  # strengths x frames x 3j x 3j
        u = UD @ bm[sel][None, :, :, None]  # U_t H^-1 b_t
        logdet += np.linalg.slogdet(S)[1].sum(1)
        quad += (u[..., 0] * np.linalg.solve(S, u)[..., 0]).sum((1, 2))
    q = c.sum() - quad
    return -0.5 * (dof * np.log(q / dof) + logdet - len(Z) * (m * np.log(grid) + logdet_p))
