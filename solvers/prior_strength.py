"""Choosing a prior's strength by held-out markers, cheaply and causally.

Each frame, one candidate strength is tried with one fold of markers held out: the bounded fit on
the other markers predicts the held-out ones, and the squared error is accumulated per strength
(exponentially discounted when streaming). The strength with the least mean held-out error is
used. Cross-validation over markers instead of frames, because the data term of one frame is what
a prior competes with (Lewis et al. 2014 §7.9 on choosing regularisation; Golub, Heath & Wahba 1979
for the held-out principle).
"""

from __future__ import annotations

import numpy as np

from solvers.qp import FrameQP

BEGIN_PASSES = 2  # marker-space trials: passes run on the frame the trial is due, the rest on the next


class HeldOutStrength:
    """``observe(target, valid)`` once per frame; ``best`` is the current choice (index into ``grid``)."""

    def __init__(self, basis: np.ndarray, lower: np.ndarray, upper: np.ndarray, mean: np.ndarray,
                 precision: np.ndarray, grid: np.ndarray, folds: int = 5, decay: float = 1.0, seed: int = 0) -> None:
        self.basis = np.asarray(basis, float)
        n = self.basis.shape[0] // 3
        self.grid = np.asarray(grid, float)
        self.qps = [FrameQP(basis, lower, upper, prior=(mean, precision), prior_weight=float(a)) for a in self.grid]
        self.fold_of = np.random.default_rng(seed).permutation(n) % folds
        self.folds, self.decay = folds, decay
        self._fold_markers = [np.flatnonzero(self.fold_of == f) for f in range(folds)]
        self._outside = [self.fold_of != f for f in range(folds)]
        self._fold_rows = [np.flatnonzero(np.repeat(self.fold_of == f, 3)) for f in range(folds)]
        self._fold_basis = [self.basis[r] for r in self._fold_rows]  # the rows a trial predicts when all are seen
        self.err = np.zeros(len(self.grid))
        self.count = np.zeros(len(self.grid))
        self.t = 0
        self.best = len(self.grid) // 2
        for qp in self.qps:  # expensive preparation once: each fold's workspace, not on the first frames
            for f in range(folds):
                qp.step(np.zeros(3 * n), self.fold_of != f)
            qp.reset()
            qp.prepare_marker_space()

    def _next(self, valid: np.ndarray) -> tuple[int, int, np.ndarray, np.ndarray]:
        """The next trial's strength, fold, held-out markers seen (of the fold's) and training pattern."""
        g = self.t % len(self.grid)
        f = (self.t // len(self.grid)) % self.folds
        return g, f, valid[self._fold_markers[f]], valid & self._outside[f]

    def prepare(self, valid: np.ndarray) -> bool:
        """Build the next trial's workspace if its training pattern is new to its QP (about half a trial's cost on
        one) and say whether it did: a streamed caller then ``observe``s the same markers on the next frame, so that
        no frame carries a whole trial on a new pattern (issue 39)."""
        g, _, seen, train = self._next(np.asarray(valid, bool))
        qp = self.qps[g]
        if not seen.any() or np.count_nonzero(train) < 3 or qp.knows(train):
            return False
        qp.prepare(train)
        return True

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
        return qp.begin(target, train, BEGIN_PASSES)

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
        w = self.qps[g].step(target, train)
        rows = self._fold_rows[f] if n_held == len(seen) else self._fold_rows[f][np.repeat(seen, 3)]
        basis = self._fold_basis[f] if n_held == len(seen) else self.basis[rows]
        r = basis @ w - np.asarray(target, float).reshape(-1)[rows]
        self.err *= self.decay ** elapsed
        self.count *= self.decay ** elapsed
        self.err[g] += float(r @ r)
        self.count[g] += n_held
        if (self.count > 0).all():
            self.best = int(np.argmin(self.err / self.count))
