"""What a marker layout can see of a rig: the singular structure of the marker basis B.

A shape is observable when moving its weight moves the markers by clearly more than their
noise, and distinguishable when no other shape (or blend of shapes) moves them the same way.
Both are properties of B (3n x m) alone (Lewis et al. 2014 §5.2 on non-orthogonal bases;
Seol et al. 2012 §3 on corresponding points). With marker noise sigma, the per-frame least-
squares estimate has covariance sigma^2 (B^T B)^-1: its diagonal is each shape's noise floor,
and right singular vectors with small singular values are the blends noise drives freely.

The report feeds the solvers through ``noise_floor`` (per-shape standard deviation under a
ridge, used as a rest-pull threshold) and ``tying_prior`` (a penalty on the difference of nearly
indistinguishable pairs, so noise cannot trade one for the other).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class ObservabilityReport:
    names: list[str]
    singular_values: np.ndarray  # r, descending
    directions: np.ndarray  # m x r right singular vectors (blends of shapes)
    displacement: np.ndarray  # m: largest marker displacement (mm) per unit weight
    marker_count: np.ndarray  # m: markers moving more than ``seen_mm`` per unit weight
    noise_sd: np.ndarray  # m: weight standard deviation per frame at the given noise (lam = 0)
    pairs: list[tuple[int, int, float]]  # (i, j, cosine) of nearly parallel columns
    noise_mm: float
    seen_mm: float
    held: list[int] = field(default_factory=list)  # quiet_shapes at noise_mm: held in every mode (issue 35.3)
    own_sd: np.ndarray | None = None  # m: weight sd per frame from the shape's own part alone (``unique_evidence``)

    @property
    def condition(self) -> float:
        s = self.singular_values
        return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")

    def unobservable(self, threshold: float = 1.0) -> list[int]:
        """Indices of singular directions whose weight noise sd exceeds ``threshold`` (weight units)."""
        sd = self.noise_mm / np.maximum(self.singular_values, 1e-300)
        return [k for k in range(len(sd)) if sd[k] > threshold]

    def describe_direction(self, k: int, top: int = 3) -> str:
        v = self.directions[:, k]
        idx = np.argsort(-np.abs(v))[:top]
        return " ".join(f"{v[i]:+.2f} {self.names[i]}" for i in idx)

    def lines(self, top_pairs: int = 12) -> list[str]:
        """The human-readable report printed by ``livecap info --observability``."""
        s = self.singular_values
        out = [f"observability: {len(self.names)} shapes, rank {int(np.sum(s > s[0] * 1e-9))}, "
               f"condition {self.condition:.3g}, marker noise {self.noise_mm:g} mm",
               f"  singular values (mm per unit weight): max {s[0]:.2f}, median {np.median(s):.2f}, min {s[-1]:.3g}",
               f"  {'shape':24s} {'max disp mm':>11s} {'markers':>7s} {'noise sd':>8s} {'own sd':>7s}"]
        own = self.own_sd if self.own_sd is not None else np.full(len(self.names), np.nan)
        for i in np.argsort(-self.noise_sd):
            flag = "  << noise-driven" if self.noise_sd[i] > 0.1 else ""
            out.append(f"  {self.names[i]:24s} {self.displacement[i]:11.2f} {self.marker_count[i]:7d} "
                       f"{self.noise_sd[i]:8.3f} {own[i]:7.3f}{flag}")
        out.append("  (own sd: from what no non-negative blend of the other shapes makes, in the per-marker noise when "
                   "known; under model mismatch every mode trusts a weight as far as that part is seen)")
        out.append(f"  nearly indistinguishable pairs (column cosine >= {PAIR_COSINE:g}): {len(self.pairs)}")
        for i, j, c in self.pairs[:top_pairs]:
            out.append(f"    {self.names[i]} ~ {self.names[j]}  cos {c:.3f}")
        weak = self.unobservable()
        out.append(f"  directions with weight noise sd > 1 per frame: {len(weak)}")
        for k in weak[:6]:
            out.append(f"    s={s[k]:.3g}: {self.describe_direction(k)}")
        out.append(f"  held in every mode at {self.noise_mm:g} mm (at rest, or the prior's conditional mean): "
                   + (", ".join(self.names[i] for i in self.held) or "none"))
        return out


PAIR_COSINE = 0.9


def observability(basis: np.ndarray, names: list[str], noise_mm: float = 0.5, seen_mm: float = 1.0,
                  pair_cosine: float = PAIR_COSINE, marker_noise: np.ndarray | None = None) -> ObservabilityReport:
    """Singular structure, per-shape displacement and noise floor, and near-duplicate pairs of B; each shape's
    own part (``unique_evidence``, per-marker ``marker_noise`` when given) up to ``MAX_QUIET_SHAPES`` shapes."""
    B = np.asarray(basis, dtype=np.float64)
    m = B.shape[1]
    if len(names) != m:
        raise ValueError(f"{len(names)} names for a basis with {m} shapes")
    _, s, Vt = np.linalg.svd(B, full_matrices=False)
    per_marker = np.linalg.norm(B.reshape(-1, 3, m), axis=1)  # n x m
    disp = per_marker.max(axis=0)
    count = (per_marker > seen_mm).sum(axis=0)
    sd = noise_floor(B, noise_mm, 0.0)
    norms = np.linalg.norm(B, axis=0)
    Bn = B / np.maximum(norms, 1e-12)
    C = Bn.T @ Bn
    pairs = [(i, j, float(C[i, j])) for i in range(m) for j in range(i + 1, m) if C[i, j] >= pair_cosine]
    pairs.sort(key=lambda p: -p[2])
    own = None
    if m <= MAX_QUIET_SHAPES and noise_mm > 0:
        d = unique_evidence(B, noise_mm, marker_noise)[1]
        own = np.divide(1.0, d, out=np.full(m, np.inf), where=d > 0)
    return ObservabilityReport(list(names), s, Vt.T, disp, count.astype(int), sd, pairs, float(noise_mm),
                               float(seen_mm), quiet_shapes(B, noise_mm).tolist(), own)


def noise_floor(basis: np.ndarray, noise_mm: float, ridge: float | np.ndarray = 0.0) -> np.ndarray:
    """Per-shape weight standard deviation of the ridge estimate under white marker noise.

    cov = sigma^2 (B^T B + L)^-1 B^T B (B^T B + L)^-1, L = diag(ridge); a pseudo-inverse when
    ridge is 0 and B is rank deficient (then the unobservable part is reported as infinite).
    """
    B = np.asarray(basis, dtype=np.float64)
    G = B.T @ B
    m = G.shape[0]
    L = np.diag(np.broadcast_to(np.asarray(ridge, dtype=np.float64), (m,)))
    if np.all(np.diag(L) == 0):
        w, V = np.linalg.eigh(G)
        tiny = w <= w.max() * 1e-12
        inv = np.where(tiny, 0.0, 1.0 / np.where(tiny, 1.0, w))
        var = (V * V) @ inv
        var = np.where(np.abs(V[:, tiny]).max(axis=1, initial=0.0) > 1e-6, np.inf, var)
        return noise_mm * np.sqrt(var)
    Hi = np.linalg.inv(G + L)
    cov = Hi @ G @ Hi
    return noise_mm * np.sqrt(np.clip(np.diag(cov), 0.0, None))


def tying_prior(report: ObservabilityReport, strength: float) -> np.ndarray:
    """m x m penalty ``strength * sum_pairs c_ij (w_i - w_j)^2`` over nearly indistinguishable pairs.

    Noise moves such a pair in opposite directions (the difference is what the markers barely
    see); the penalty ties the difference while leaving the pair's sum free.
    """
    m = len(report.names)
    P = np.zeros((m, m))
    for i, j, c in report.pairs:
        P[i, i] += c
        P[j, j] += c
        P[i, j] -= c
        P[j, i] -= c
    return strength * P


QUIET_SD = 1.0  # a shape whose per-frame weight noise sd exceeds this (the weight range) is not seen by the markers


MAX_QUIET_SHAPES = 400  # above this many shapes the analysis (one NNLS per shape per removal) is skipped


def quiet_shapes(basis: np.ndarray, noise_mm: float, threshold: float = QUIET_SD) -> np.ndarray:
    """Shapes the markers cannot tell apart from noise and from the other shapes, removed greedily (of those whose
    noise sd exceeds ``threshold``, the one that moves the markers least, then the rest re-measured: of two nearly
    parallel shapes the weaker goes and its partner then carries their common motion). Indices, ascending.

    Per-frame least squares gives shape k a weight sd of ``sigma / d_k``, ``d_k`` the distance of its marker motion
    from the span of the others (module docstring: the diagonal of ``sigma^2 (B^T B)^-1``). The weights are
    non-negative, so here ``d_k`` is the distance from the others' *cone* (NNLS): jawLeft and jawRight move the
    markers in opposite directions and stay apart; eyeWide and eyeLookUp (cosine 0.94 on the ICT rig) do not.

    Issue 35.3: shapes left free here become a dustbin for whatever the rig cannot explain (eye gaze, frowns on a
    real capture); held at rest or at the prior's conditional mean, that misfit stays in the residual."""
    from scipy.optimize import nnls

    B = np.asarray(basis, dtype=np.float64)
    m = B.shape[1]
    if m < 2 or m > MAX_QUIET_SHAPES or not noise_mm > 0:
        return np.zeros(0, dtype=int)
    norms = np.linalg.norm(B, axis=0)
    keep = list(range(m))
    out = []
    while len(keep) > 1:
        dist = np.array([nnls(B[:, [i for i in keep if i != k]], B[:, k])[1] for k in keep])
        sd = noise_mm / np.maximum(dist, 1e-300)
        over = np.flatnonzero(sd > threshold)
        if not len(over):
            break
        j = int(over[np.argmin(norms[np.asarray(keep)[over]])])  # the weakest of them: it moves the markers least
        out.append(keep.pop(j))
    return np.sort(np.asarray(out, dtype=int))


def whiten(basis: np.ndarray, noise_mm: float, marker_noise: np.ndarray | None) -> np.ndarray:
    """B in units of the marker noise: each marker's rows divided by its own noise sd (``marker_noise``, n: its
    shape across markers, rescaled to RMS ``noise_mm``; a marker counts as at least ``MARKER_NOISE_FLOOR`` of the
    noisiest), or by ``noise_mm`` when ``None``.

    The honest per-marker noise (calibration's fit residual, ``livecap.modes.robust.tune_profile``) is largest
    where the rig cannot follow the actor (the mouth and chin on a real capture, issue 35.1): motion there counts
    for less."""
    B = np.asarray(basis, dtype=np.float64)
    if marker_noise is None:
        return B / float(noise_mm)
    s = np.asarray(marker_noise, dtype=np.float64)
    if s.shape != (B.shape[0] // 3,) or not np.all(np.isfinite(s)) or not s.max() > 0:
        raise ValueError(f"marker_noise: {B.shape[0] // 3} positive values expected (one per marker), "
                         f"got shape {s.shape}")
    s = np.maximum(s, MARKER_NOISE_FLOOR * s.max())
    s = s * (float(noise_mm) / np.sqrt(np.mean(s**2)))  # its shape across markers, at the noise in use (--noise-mm)
    return B / np.repeat(s, 3)[:, None]


MARKER_NOISE_FLOOR = 0.1  # an exactly fitted marker is not noiseless: at least this share of the noisiest one


def unique_evidence(basis: np.ndarray, noise_mm: float, marker_noise: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Per shape, what of its marker motion no non-negative blend of the other shapes makes (its *unique*
    direction: the NNLS residual of its whitened column against the others', ``whiten``), as ``(E, d)``: ``E``
    (m x 3n) maps a marker residual (mm, flattened) to the evidence along each unique direction in noise sd units;
    ``d`` (m) is the unique motion per unit weight in noise sd units (``1 / d``: the weight's per-frame sd).

    Issue 35: a shape that is nearly a blend of partners takes up the partners' model mismatch; its weight is
    worth trusting only as far as the markers move along what it alone explains, by more than the noise there
    (``livecap.modes.quiet.EvidenceGate``). Non-negative blends, as ``quiet_shapes``: jawLeft is not -jawRight."""
    from scipy.optimize import nnls

    Bw = whiten(basis, noise_mm, marker_noise)
    m = Bw.shape[1]
    U = np.array(Bw.T)
    for k in range(m if m > 1 else 0):
        others = np.delete(Bw, k, axis=1)
        U[k] -= others @ nnls(others, Bw[:, k])[0]
    d = np.linalg.norm(U, axis=1)
    per_mm = whiten(np.ones((Bw.shape[0], 1)), noise_mm, marker_noise)[:, 0]  # 1 / noise sd per coordinate
    return U / np.maximum(d, 1e-300)[:, None] * per_mm[None, :], d
