"""The whole-array numpy IMM (solvers/tracking.py before it was compiled, 4eeff2c): the reference that
``solvers.imm_kernels`` is tested against (tests/test_tracking.py); benchmarks/numba_ab.py loads it from git."""

from __future__ import annotations

import numpy as np

from solvers.tracking import IMMFilter


class NumpyIMMFilter(IMMFilter):
    """IMM of two constant-velocity models per channel: 'hold' (process noise ``q_hold``) and 'move'
    (``q_move``), Markov switching with mean sojourn ``sojourn_frames`` in either mode
    (Bar-Shalom et al. 2001 §11.6.6: interaction/mixing, mode-matched filtering, mode probability
    update, combination). The output is the probability-weighted mean of the two models' values.

    With two models the mixing has a closed form per channel: with ``a_j = P(hold before | j now)``
    the mixed mean is ``x_move + a_j (x_hold - x_move)`` and the spread-of-means term of the mixed
    covariance is ``a_j (1 - a_j) d d'`` (d the difference of the two means), so a step is ~40
    whole-array operations on preallocated buffers, all channels and both models at once.
    """

    _PREDICT = np.array([[1.0, 2.0, 1.0], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]])  # F P F' on (p00, p01, p11)

    def reset(self) -> None:
        self._shape: tuple | None = None
        self._mu: np.ndarray | None = None  # (2, channels) mode probabilities

    @property
    def move_probability(self) -> np.ndarray | None:
        """Each channel's current probability of the 'move' model (diagnostics)."""
        return None if self._mu is None else self._mu[1].reshape(self._shape)

    def _start(self, y: np.ndarray, ok: np.ndarray) -> np.ndarray:
        """Both models at the first sample (variance r, velocity 0 with variance r); buffers allocated."""
        self._shape = y.shape
        C = y.size
        r = np.broadcast_to(self.r, y.shape).reshape(C).copy()
        start = np.where(ok, y, 0.0).reshape(C)
        self._r = r
        self._X = np.zeros((2, 2, C))  # (value, velocity) x (hold, move) x channel
        self._X[0] = start
        self._P = np.zeros((3, 2, C))  # (p00, p01, p11) x model x channel
        self._P[0] = r
        self._P[2] = r
        q = np.stack([np.broadcast_to(qm, y.shape).reshape(C) for qm in self.q])
        self._Q = np.stack([q / 4, q / 2, q])  # DWNA: G q G' with G = (1/2, 1)
        self._mu = np.stack([np.full(C, 1 - self.p_move), np.full(C, self.p_move)])
        self._piT = self.transition.T.copy()
        self._pi_hold = self.transition[0].reshape(2, 1).copy()
        self._Xn, self._Pn, self._T3 = np.empty_like(self._X), np.empty_like(self._P), np.empty_like(self._P)
        self._c, self._a, self._b, self._d = (np.empty((2, C)) for _ in range(4))
        self._S, self._E, self._L, self._W = (np.empty((2, C)) for _ in range(4))
        self._DD, self._dP = np.empty((3, C)), np.empty((3, C))
        self._K, self._KE = np.empty((2, 2, C)), np.empty((2, 2, C))
        self._views = [self._frame_views(self._X, self._Xn), self._frame_views(self._Xn, self._X)]
        self._flip = 0
        P, Pn, d, DD = self._P, self._Pn, self._d, self._DD
        self._v = (P[:, 0], P[:, 1], P[:, 1:2], P.reshape(3, -1), Pn.reshape(3, -1), P[0], P[1], P[2], P[:2],
                   d[0], d[:, None], self._dP[:, None], DD[:2], DD[2], DD[:, None], self._K[1],
                   self._mu[0], self._mu[1], self._L[0], self._L[1])
        return start.reshape(y.shape).copy()

    @staticmethod
    def _frame_views(X: np.ndarray, Xn: np.ndarray) -> tuple:
        """Views of the state (X) and next state (Xn) buffers, made once: a step swaps the two."""
        return X, Xn, X[:, 0], X[:, 1], X[:, 1:2], Xn[0], Xn[1]

    def step(self, y: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        y = np.asarray(y, dtype=np.float64)
        ok = None if valid is None else np.broadcast_to(np.asarray(valid, bool), y.shape).reshape(-1)
        if self._mu is None:
            return self._start(y, np.ones(y.shape, bool) if ok is None else ok.reshape(y.shape))
        if ok is not None and ok.all():
            ok = None
        X, Xn, X_hold, X_move, X_move_b, Xn_x, Xn_v = self._views[self._flip]
        (P_hold, P_move, P_move_b, P3, Pn3, P00, P01, P11, P0_1, d0, d_b, dP_b, DD01, DD2, DD_b, K1,
         mu0, mu1, L0, L1) = self._v
        P, mu, a, b, d = self._P, self._mu, self._a, self._b, self._d
        Pn, c, S, E, L, K, KE = self._Pn, self._c, self._S, self._E, self._L, self._K, self._KE
        # interaction: a_j = P(hold before | j now), mixed means and covariances per model j
        np.matmul(self._piT, mu, out=c)
        np.multiply(self._pi_hold, mu0, out=a)
        a /= c
        np.subtract(X_hold, X_move, out=d)
        np.multiply(a, d_b, out=Xn)
        Xn += X_move_b
        np.multiply(a, a, out=b)
        np.subtract(a, b, out=b)
        np.multiply(d0, d, out=DD01)
        np.multiply(d[1], d[1], out=DD2)
        np.subtract(P_hold, P_move, out=self._dP)
        np.multiply(a, dP_b, out=Pn)
        Pn += P_move_b
        np.multiply(b, DD_b, out=self._T3)
        Pn += self._T3
        # mode-matched prediction (DWNA constant velocity) and update
        Xn_x += Xn_v
        np.matmul(self._PREDICT, Pn3, out=P3)
        P += self._Q
        np.add(P00, self._r, out=S)
        np.divide(P0_1, S, out=K)
        np.subtract(y.reshape(-1), Xn_x, out=E)
        if ok is not None:  # a missing sample (possibly NaN) is predicted through: no update
            E[:, ~ok] = 0.0
            K[:, :, ~ok] = 0.0
        np.multiply(K, E, out=KE)
        Xn += KE
        np.multiply(K1, P01, out=L)
        P11 -= L
        np.divide(self._r, S, out=L)
        if ok is not None:
            L[:, ~ok] = 1.0
        P0_1 *= L
        # mode probabilities from the innovation likelihoods, then the combined output
        np.multiply(E, E, out=L)
        L /= S
        L *= -0.5
        np.exp(L, out=L)
        np.multiply(S, 2 * np.pi, out=self._W)
        np.sqrt(self._W, out=self._W)
        L /= self._W
        if ok is not None:
            L[:, ~ok] = 1.0
        np.multiply(c, L, out=mu)
        mu += 1e-300
        np.add(mu0, mu1, out=L0)
        mu /= L0
        self._flip ^= 1
        self._X = Xn
        np.multiply(mu, Xn_x, out=L)
        return np.add(L0, L1).reshape(self._shape)

    def filter(self, Y: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """Run over a sequence (T, ...) from a fresh state; the same numbers as calling ``step``."""
        self.reset()
        return np.stack([self.step(y, None if valid is None else valid[t]) for t, y in enumerate(np.asarray(Y))])
