"""Choosing a prior's strength by held-out markers, cheaply and causally.

Each frame, one candidate strength is tried with one fold of markers held out: the bounded fit on
the other markers predicts the held-out ones, and the squared error is accumulated per strength
(exponentially discounted when streaming). The strength with the least mean held-out error is
used. Cross-validation over markers instead of frames, because the data term of one frame is what
a prior competes with (Lewis et al. 2014 §7.9 on choosing regularisation; Golub, Heath & Wahba 1979
for the held-out principle). A whole take: every strength on every frame at once, unbounded, in closed
form (:func:`take_strength`).
"""

from __future__ import annotations

import math

import numpy as np

from solvers.prior_strength_kernels import held_out_error, score, unbounded_trial
from solvers.prior_support import hidden_rows
from solvers.qp import FrameQP

BEGIN_PASSES = 2  # marker-space trials: passes owed to the frame the trial is due, the rest on the next
BEGIN_NOW = 1  # of them run there, with the next one's factor; the finishing frame runs the others (the same passes)


class HeldOutStrength:
    """``observe(target, valid)`` once per frame; ``best`` is the current choice (index into ``grid``)."""

    def __init__(self, basis: np.ndarray, lower: np.ndarray, upper: np.ndarray, mean: np.ndarray,
                 precision: np.ndarray, grid: np.ndarray, folds: int = 5, decay: float = 1.0, seed: int = 0,
                 unbounded: bool = False, frame_passes: int = 0, weakest_within: bool = False) -> None:
        """``unbounded``: also build the maps of :meth:`observe_unbounded` (a streamed selector's trials);
        ``frame_passes``: the trial fits' passes a frame in marker space (``solvers.qp.FrameQP``);
        ``weakest_within``: choose by :func:`weakest_within` rather than the least mean error."""
        self.basis = np.asarray(basis, float)
        self.lower, self.upper = np.asarray(lower, float), np.asarray(upper, float)
        n = self.basis.shape[0] // 3
        self.grid = np.asarray(grid, float)
        self.qps: list[FrameQP] = []
        for a in self.grid:  # one B'M^2 read by every strength's trial (``like``: 1.7 MB at 72 x 1000, not five)
            self.qps.append(FrameQP(basis, lower, upper, prior=(mean, precision), prior_weight=float(a),
                                    frame_passes=frame_passes, like=self.qps[0] if self.qps else None))
        self.fold_of = np.random.default_rng(seed).permutation(n) % folds
        self.folds, self.decay = folds, decay
        self._fold_markers = [np.flatnonzero(self.fold_of == f) for f in range(folds)]
        self._outside = [self.fold_of != f for f in range(folds)]
        self.err = np.zeros(len(self.grid))
        self.count = np.zeros(len(self.grid))
        self._counted = False
        self.t = 0
        self.best = len(self.grid) // 2
        self.unbounded, self.weakest_within = unbounded, weakest_within
        self._maps = self._unbounded_maps(np.asarray(mean, float), np.asarray(precision, float)) if unbounded else {}
        for qp in self.qps:  # expensive preparation once: each fold's workspace, not on the first frames
            for f in range(folds):
                qp.step(np.zeros(3 * n), self.fold_of != f)
            qp.reset()
            qp.prepare_marker_space()

    def carry(self, other: HeldOutStrength) -> None:
        """Start from ``other``'s held-out errors and choice (the same grid and folds, under a prior moved by a check
        against the actor): the strength chosen so far is kept rather than restarted at the grid's middle."""
        self.err, self.count, self.t, self.best = other.err.copy(), other.count.copy(), other.t, other.best

    def _next(self, valid: np.ndarray) -> tuple[int, int, np.ndarray, np.ndarray]:
        """The next trial's strength, fold, held-out markers seen (of the fold's) and training pattern."""
        g = self.t % len(self.grid)
        f = (self.t // len(self.grid)) % self.folds
        return g, f, valid[self._fold_markers[f]], valid & self._outside[f]

    def _unbounded_maps(self, mean: np.ndarray, precision: np.ndarray) -> dict:
        """Per strength and fold: the training rows (every marker outside the fold) and the fit without bounds on
        them, w = G x + h (G = H^-1 B_o', h = H^-1 a P mu, H = B_o'B_o + a P): one solve each, here, once; G kept
        transposed (rows x m, the compiled trial's order)."""
        maps = {}
        for g, a in enumerate(self.grid):
            for f in range(self.folds):
                rows = np.flatnonzero(np.repeat(self._outside[f], 3))
                Bo = self.basis[rows]
                Gh = np.linalg.solve(Bo.T @ Bo + a * precision, np.column_stack([Bo.T, a * precision @ mean]))
                maps[g, f] = (rows, np.ascontiguousarray(Gh[:, :-1].T), np.ascontiguousarray(Gh[:, -1]))
        return maps

    def begin(self, target: np.ndarray, valid: np.ndarray, start: np.ndarray) -> bool:
        """Run the first BEGIN_PASSES passes of the next trial now where its QP takes the marker-space path
        (solvers.marker_space_qp: each may refactor its 216 x 216 matrix) and say whether it did: the caller's
        ``observe`` of the same markers from the same start then continues from them (the same score), so that a
        trial's cost is shared by two frames (issue 39, 72 x 1000)."""
        g, _, seen, train = self._next(np.asarray(valid, bool))
        qp = self.qps[g]
        if not qp.marker_space or not seen.any() or np.count_nonzero(train) < 3:
            return False
        qp.warm(start)
        return qp.begin(target, train, BEGIN_PASSES, BEGIN_NOW)

    def observe(self, target: np.ndarray, valid: np.ndarray, start: np.ndarray | None = None,
                elapsed: float = 1.0) -> None:
        """``start``: a solution near this frame's (e.g. the last frame's fit) to start the trial's QP from;
        by default the trial starts from this strength's last trial, ``len(grid)`` trials ago. ``elapsed``: the
        frames since the last trial, in ``decay``'s unit (a streamed caller whose trials come unevenly)."""
        valid = np.asarray(valid, bool)
        g, f, seen, train = self._next(valid)  # seen: the fold's markers seen, those held out
        self.t += 1
        n_held = int(np.count_nonzero(seen))
        if not n_held or np.count_nonzero(train) < 3:
            return
        if start is not None:
            self.qps[g].warm(start)
        target = np.asarray(target, dtype=np.float64).reshape(-1)
        w = self.qps[g].step(target, train)
        err = held_out_error(self.basis, self._fold_markers[f], seen, w, target)
        self._score(g, err, n_held, elapsed)

    def observe_unbounded(self, target: np.ndarray, valid: np.ndarray, fill: np.ndarray, elapsed: float = 1.0) -> None:
        """The streamed trial (issue 39): the fit without its bounds, clipped to them, on every marker outside the
        fold, those this frame misses predicted by ``fill`` (the frame's own fit): a fixed linear map per strength
        and fold instead of a bounded QP on a training pattern its QP has never seen (with occlusion in bursts,
        nearly every one: a new workspace and a cold factor, most of kalman's streamed p99). ICT, six real
        performances: streamed weight RMSE and vertex p95 as the bounded trial's, or lower (docs/performance.md,
        "`kalman`'s streamed trial without bounds")."""
        g = self.t % len(self.grid)
        f = (self.t // len(self.grid)) % self.folds
        self.t += 1
        rows, GT, h = self._maps[g, f]
        best = unbounded_trial(target.reshape(-1), valid, self.basis, fill, rows, GT, h, self.lower, self.upper,
                               self._fold_markers[f], g, self.decay ** elapsed, self.err, self.count, self._counted)
        if best >= 0:
            self._counted = True
            self.best = weakest_within(self.err, self.count, best) if self.weakest_within else best

    def _score(self, g: int, err: float, n_held: int, elapsed: float) -> None:
        best = score(self.err, self.count, g, float(err), float(n_held), self.decay ** elapsed, self._counted)
        if best >= 0:  # (decayed counts stay > 0: checked until they are)
            self._counted = True
            self.best = weakest_within(self.err, self.count, best) if self.weakest_within else best


def weakest_within(err: np.ndarray, count: np.ndarray, best: int) -> int:
    """The weakest strength whose mean held-out error (``err / count`` per strength, ``count`` held-out markers, the
    grid weakest first) is within one standard error of the least, ``best``'s: the one-standard-error rule (Breiman
    et al. 1984 §3.4.3; Hastie, Tibshirani & Friedman 2009 §7.10), turned toward the model that assumes less. With an
    animation prior the assumption is the prior's mean, learned from other performers and least known for this actor
    along the directions the markers see weakly, which held-out markers cannot score (issue 41: the streamed choice
    ran about one grid step stronger than the weight error's best, docs/robustness.md). The standard error is the
    noise model's: a held-out marker's error is three Gaussian coordinates squared, so the mean over n markers has
    relative standard error sqrt(2 / 3n). (In Python floats: nine numbers a streamed trial, ~0.55 us; numpy ~2.5-3.3)"""
    e, n = err.tolist(), count.tolist()
    if not n[best] > 0:  # (a strength never scored: the kernel's choice)
        return best
    bound = e[best] / n[best] * (1.0 + math.sqrt(2.0 / (3.0 * n[best])))
    for k in range(best):
        if n[k] > 0 and e[k] <= bound * n[k]:
            return k
    return best





# take_strength: frames missing at most this many training markers (their cost grows with its square; issue 39 item 2:
# 4 -> 2 halved it on a 30 s ICT take, 33 -> 17 ms a pass, the same weights there and in realeval with a prior)
FEW_MISSING = 2


def take_strength(basis: np.ndarray, mean: np.ndarray, precision: np.ndarray, grid: np.ndarray, targets: np.ndarray,
                  valid: np.ndarray, folds: int = 5, seed: int = 0,
                  factors: dict | None = None) -> tuple[int, np.ndarray, int]:
    """A whole take's strength by the held-out markers of :class:`HeldOutStrength` (its folds), every strength on
    every frame, in closed form: the index into ``grid`` of the least mean held-out squared error, those errors, and
    the frames they were measured on.

    Frame t holds out fold ``t % folds``. With every other marker seen, the fit at strength a is
    w(a) = mean + (G + a P)^-1 B'(s - B mean), G = B'B over the training rows; with G = L L' and
    L^-1 P L^-T = Q diag(d) Q', (G + a P)^-1 = M diag(1 / (1 + a d)) M' for M = L^-T Q: one Cholesky and one
    eigendecomposition per fold serve every strength and every frame (the pair's generalised eigenproblem; Golub &
    Van Loan 2013 §8.7). A frame's k unseen training markers take their rows U' out of G: (H - U U')^-1 by
    Woodbury (ibid. §2.1.4), a 3k x 3k solve per strength and frame. The frames used: those missing at most
    FEW_MISSING training markers, or, where they are fewer, the third of the fold's frames that miss the fewest.
    So the trials are matrix products over the take instead of a bounded QP per frame. The fits are unbounded:
    clipped to the bounds they chose worse, and solved within them they cost that QP per frame (issue 39,
    docs/performance.md). ``factors``: a dict that keeps each fold's (M, d) for the next call on the same basis
    and prior (a second pass over the take), and, for a next call on the same validity and grid, each fold's frames
    and their Woodbury systems, which depend on the markers' validity and not on where they are (issue 39 item 2: the
    second pose pass moves the markers rigidly, the validity stays)."""
    B = np.asarray(basis, float)
    n3, m = B.shape
    n = n3 // 3
    T = len(valid)
    ok = np.asarray(valid, bool).reshape(T, n)
    Z = np.where(np.repeat(ok, 3, axis=1), np.asarray(targets, float).reshape(T, n3) - B @ np.asarray(mean, float),
                 0.0)
    grid = np.asarray(grid, float)
    fold_of = np.random.default_rng(seed).permutation(n) % folds
    kept = {} if factors is None else factors
    if "valid" not in kept or not (np.array_equal(kept["valid"], ok) and np.array_equal(kept["grid"], grid)):
        for f in range(folds):
            kept.pop(("plan", f), None)
        kept["valid"], kept["grid"] = ok.copy(), grid.copy()
    err, count, used = np.zeros(len(grid)), 0.0, 0
    for f in range(folds):
        held = fold_of == f
        train = np.repeat(~held, 3)
        if f not in kept:
            Bt = B[train]
            G = Bt.T @ Bt
            L = np.linalg.cholesky(G + 1e-12 * np.trace(G) / m * np.eye(m))
            Li = np.linalg.solve(L, np.eye(m))
            d, Q = np.linalg.eigh(Li @ np.asarray(precision, float) @ Li.T)
            kept[f] = Li.T @ Q, d
        M, d = kept[f]
        D = 1.0 / (1.0 + grid[:, None] * np.maximum(d, 0.0))  # strengths x m
        if ("plan", f) not in kept:
            kept["plan", f] = _fold_plan(B, M, D, ok, held, f, folds)
        frames, BtM, systems, good, seen = kept["plan", f]
        if not len(frames):
            continue
        Y = D[:, None, :] * (Z[frames][:, train] @ BtM)[None]  # strengths x frames x m: H^-1 B'(s - B mean), M'-wise
        for sel, U, S in systems:
            X = np.linalg.solve(S, (U[None] @ Y[:, sel, :, None]))
            Y[:, sel] += D[:, None, :] * (np.swapaxes(U, 1, 2)[None] @ X)[..., 0]
        frames, Y = frames[good], Y[:, good]
        E = np.where(seen[None], Y @ (B[~train] @ M).T - Z[frames][:, ~train][None], 0.0)
        err += (E**2).sum((1, 2))
        count += float(seen.sum()) / 3
        used += len(frames)
    if factors is None:
        kept.clear()
    if not count:
        return len(grid) // 2, err, 0
    err /= count
    return int(np.argmin(err)), err, used


def _fold_plan(B: np.ndarray, M: np.ndarray, D: np.ndarray, ok: np.ndarray, held: np.ndarray, f: int,
               folds: int) -> tuple:
    """What fold ``f``'s trials need of the validity ``ok`` alone (:func:`take_strength`): its frames, the training
    rows M'-wise, per count of unseen training markers the frames' indices, unseen rows U and Woodbury matrices
    S = I - U diag(D_a) U' (strengths x frames x 3k x 3k, the frames whose seen markers fix every column), the
    frames kept, and their held-out markers seen."""
    T = len(ok)
    frames = np.arange(f, T, folds)
    frames = frames[ok[frames][:, held].any(1)]
    missing = ~ok[frames][:, ~held]
    k = missing.sum(1)
    order = np.argsort(k, kind="stable")
    keep = max(int(np.count_nonzero(k <= FEW_MISSING)), len(frames) // 3)
    frames, missing = frames[order[:keep]], missing[order[:keep]]
    BtM = B[np.repeat(~held, 3)] @ M
    systems = []
    good = np.ones(len(frames), bool)
    for sel, U in hidden_rows(BtM, ~missing):  # U: frames x 3k x m, the unseen rows, M'-wise
        S = np.eye(U.shape[1]) - (U[None] * D[:, None, None, :]) @ np.swapaxes(U, 1, 2)[None]
        sign, logdet = np.linalg.slogdet(S[0])  # the weakest strength's: every S is at least as definite
        fine = (sign > 0) & (logdet > -25.0)  # the seen markers fix every column
        systems.append((sel[fine], U[fine], np.ascontiguousarray(S[:, fine])))
        good[sel[~fine]] = False
    return frames, BtM, systems, good, np.repeat(ok[frames[good]][:, held], 3, axis=1)
