"""The prior's form against its strength, in hindsight (issue 41.2): how far can one strength per take, or one
strength per band of directions, bring ICT's offline ``kalman`` RMSE with a prior?

Leave one file out over ../shared/realdata/performance (the prior from the other files, as ``livecap realeval``
builds it), each take solved offline by ``kalman`` as ``livecap solve`` does, its prior checked against the take as
today. Rows per take, weight RMSE x the oracle's:

- ``chosen``: the strength ``take_strength`` picks (today's code);
- ``scalar``: the best of the 9 grid strengths (``marker_kalman.STRENGTHS``) in hindsight;
- ``bands``: the checked prior's precision P split along the generalised eigen-directions of (P, B'B) -- L^-1 P L^-T
  = Q diag(d) Q' for B'B = L L' (Golub & Van Loan 2013 §8.7), d the prior's precision over the markers' information
  per direction, so a large d is a direction the markers see weakly -- into ``--bands`` equal-count bands by d, and
  each band's strength picked from the same grid in hindsight by coordinate descent from the best scalar
  (``--sweeps`` passes over the bands).

``--mean`` / ``--cov`` swap the checked prior's mean / covariance for the take's own no-prior fit's (no truth), a
pooled or noise-corrected form of it, or the take's true ones (ceilings); ``--extend`` adds strengths to the grid.
Two covariances by the markers' evidence (no truth): ``--cov em``, the covariance that maximises the marginal
likelihood of the check's frames about the checked mean (EM, regularised toward the others' covariance by an
inverse-Wishart hyperprior of ``--em-prior`` x the frames' number), and ``--cov mix``, the others' files grouped by
performer, one prior each, mixed by each one's marginal likelihood on the check's frames (then checked as today);
``mixem`` both. Each row also gives ``truth_nll``, the true weights' negative log density under the prior used.
The truth picks every hindsight choice: these rows bound what a criterion choosing that form could reach; they are
not a mode.

    python -m benchmarks.prior_oracle [--noise 0.5 0.2] [--seconds 10] [--bands 3] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time
from pathlib import Path

import numpy as np


def band_precisions(basis: np.ndarray, precision: np.ndarray, bands: int) -> tuple[list[np.ndarray], np.ndarray]:
    """P = sum_b P_b, each P_b the prior's precision along one band of generalised eigen-directions of (P, B'B),
    the bands equal in count, ordered from the directions the markers see best (small d) to the weakest; and d."""
    G = basis.T @ basis
    m = len(G)
    L = np.linalg.cholesky(G + 1e-12 * np.trace(G) / m * np.eye(m))
    Li = np.linalg.solve(L, np.eye(m))
    d, Q = np.linalg.eigh(Li @ precision @ Li.T)
    Minv = Q.T @ L.T  # M = L^-T Q, M' G M = I, M' P M = diag(d): P = M^-T diag(d) M^-1
    parts = np.array_split(np.arange(m), bands)
    return [Minv[idx].T @ (np.maximum(d[idx], 0.0)[:, None] * Minv[idx]) for idx in parts], d


def denoised(C: np.ndarray, basis: np.ndarray, noise_mm: float, floor: float = 1e-2) -> np.ndarray:
    """A fit's weight covariance less the per-frame fit noise N = noise^2 (B'B)^-1: in N's whitened coordinates
    its eigenvalues minus 1, kept at least ``floor`` (the moment estimate of the signal's covariance)."""
    G = basis.T @ basis
    m = len(G)
    N = noise_mm**2 * np.linalg.inv(G + 1e-9 * np.trace(G) / m * np.eye(m))
    L = np.linalg.cholesky(N)
    Li = np.linalg.solve(L, np.eye(m))
    lam, V = np.linalg.eigh(Li @ C @ Li.T)
    S = L @ V
    return (S * np.maximum(lam - 1.0, floor)) @ S.T


def _frames(basis: np.ndarray, mean: np.ndarray, targets: np.ndarray, valid: np.ndarray, extra: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per frame (of >= 3 seen markers) of x_t - B mean: D_t'D_t, D_t'x_t, |x_t|^2 and the seen coordinates' number,
    D = [B, extra] on the seen markers; and the frames kept."""
    D = np.hstack([basis, extra])
    ok = np.asarray(valid, bool)
    n3, k = D.shape
    X = np.asarray(targets, float).reshape(len(ok), n3) - basis @ mean
    rows = np.repeat(ok, 3, axis=1)
    X = np.where(rows, X, 0.0)
    keep = ok.sum(1) >= 3
    X, rows, ok = X[keep], rows[keep], ok[keep]
    Dm = D.reshape(n3 // 3, 3, k)
    PtP = np.einsum("tn,nik,nil->tkl", ok.astype(float), Dm, Dm, optimize=True)
    return PtP, X @ D, (X**2).sum(1), rows.sum(1).astype(float), keep


def evidence_cov(basis: np.ndarray, mean: np.ndarray, cov: np.ndarray, targets: np.ndarray, valid: np.ndarray,
                 extra: np.ndarray, noise_var: float, prior_frames: float, iterations: int = 100, tol: float = 1e-4
                 ) -> tuple[np.ndarray, float, int]:
    """The weights' covariance C that maximises the frames' marginal likelihood (type-II ML, Bishop 2006 §3.5)
    under w_t ~ N(mean, C), x_t = B w_t + E p_t + e_t, p_t ~ N(0, POSE_VARIANCE), e_t ~ N(0, s2 I), by EM
    (Dempster et al. 1977; Bishop 2006 §9.3 for the Gaussian latent model), with an inverse-Wishart hyperprior
    centred on ``cov`` worth ``prior_frames`` frames (its MAP: (nu cov + sum_t E[(w_t - mean)(w_t - mean)']) /
    (nu + T)); s2 estimated alongside from ``noise_var``. Returns C, s2 and the iterations run."""
    from solvers.prior_support import POSE_VARIANCE

    m = len(mean)
    PtP, b, c, count, _ = _frames(basis, mean, targets, valid, extra)
    T, k = b.shape
    C0 = np.asarray(cov, float)
    C, s2, nu = C0.copy(), float(noise_var), float(prior_frames)
    done = 0
    while done < iterations:
        done += 1
        Pinv = np.zeros((k, k))
        Pinv[:m, :m] = np.linalg.inv(C)
        Pinv[m:, m:] = np.eye(k - m) / POSE_VARIANCE
        S = np.linalg.inv(PtP / s2 + Pinv[None])
        y = np.einsum("tkl,tl->tk", S, b) / s2
        second = y[:, :m].T @ y[:, :m] + S[:, :m, :m].sum(0)
        new = (nu * C0 + second) / (nu + T)
        resid = c - 2 * (y * b).sum(1) + np.einsum("tk,tkl,tl->t", y, PtP, y) + np.einsum("tkl,tlk->t", PtP, S)
        s2 = float(max(resid.sum() / count.sum(), 1e-8))
        change = float(np.max(np.abs(new - C)) / np.max(np.diag(C)))
        C = 0.5 * (new + new.T)
        if change < tol:
            break
    return C, s2, done


def held_out_ratio(basis: np.ndarray, mean: np.ndarray, cov: np.ndarray, targets: np.ndarray, valid: np.ndarray,
                   extra: np.ndarray, noise_var: float, ratios: list[float]) -> tuple[float, list[float]]:
    """The hyperprior's weight (x the frames) whose EM covariance, fitted on one half of the take (in time), gives
    the other half the highest marginal likelihood, both ways round; and each ratio's held-out log evidence."""
    half = len(targets) // 2
    parts = [(slice(0, half), slice(half, None)), (slice(half, None), slice(0, half))]
    scores = []
    for r in ratios:
        score = 0.0
        for fit, test in parts:
            C, s2, _ = evidence_cov(basis, mean, cov, targets[fit], valid[fit], extra, noise_var,
                                    min(r, 1e9) * len(targets[fit]))
            score += log_evidence(basis, mean, C, targets[test], valid[test], extra, s2)
        scores.append(score)
    return ratios[int(np.argmax(scores))], scores


def log_evidence(basis: np.ndarray, mean: np.ndarray, cov: np.ndarray, targets: np.ndarray, valid: np.ndarray,
                 extra: np.ndarray, noise_var: float) -> float:
    """log p(frames | mean, cov): each frame's marker displacement x_t ~ N(B mean, D V D' + s2 I), V = the weights'
    cov and the pose's broad variance (Bishop 2006 §2.3.3), by the matrix determinant lemma and Woodbury in the
    k = m + 6 unknowns; the frames counted as independent."""
    from solvers.prior_support import POSE_VARIANCE

    m = len(mean)
    PtP, b, c, count, _ = _frames(basis, mean, targets, valid, extra)
    k = b.shape[1]
    Pinv = np.zeros((k, k))
    Pinv[:m, :m] = np.linalg.inv(cov)
    Pinv[m:, m:] = np.eye(k - m) / POSE_VARIANCE
    A = PtP / noise_var + Pinv[None]
    logdetV = np.linalg.slogdet(cov)[1] + (k - m) * np.log(POSE_VARIANCE)
    logdet = count * np.log(noise_var) + logdetV + np.linalg.slogdet(A)[1]
    quad = c / noise_var - np.einsum("tk,tk->t", b, np.linalg.solve(A, b[..., None])[..., 0]) / noise_var**2
    return float(-0.5 * (count * np.log(2 * np.pi) + logdet + quad).sum())


def mixture(means: list[np.ndarray], covs: list[np.ndarray], logp: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                                       np.ndarray]:
    """One Gaussian for the mixture sum_k r_k N(mean_k, cov_k), r_k the components' posterior under equal prior
    weights given their log evidences ``logp`` (its first two moments: Bishop 2006 §9.2); and r."""
    r = np.exp(logp - np.max(logp))
    r /= r.sum()
    mu = sum(rk * mk for rk, mk in zip(r, means, strict=True))
    C = sum(rk * (Ck + np.outer(mk - mu, mk - mu)) for rk, mk, Ck in zip(r, means, covs, strict=True))
    return mu, C, r


def nll(weights: np.ndarray, mean: np.ndarray, precision: np.ndarray) -> float:
    """The true weights' mean negative log density per frame (nats) under the prior N(mean, precision^-1) the solver
    used: how well the prior's form describes this take's acting, its strength aside."""
    d = weights - mean
    return float(0.5 * (np.einsum("ti,ij,tj->t", d, precision, d).mean() - np.linalg.slogdet(precision)[1]
                        + len(mean) * np.log(2 * np.pi)))


def main(argv: list[str] | None = None) -> int:
    from livecap.calibration.animation_prior import VARIANCE_FLOOR, build_prior
    from livecap.cli.realeval import _realdata, _rig
    from livecap.demo.curves_take import CurveTakeSettings, curves_take
    from livecap.modes import marker_kalman
    from livecap.modes.registry import build_solver
    from livecap.offline.metrics import weight_rmse
    from livecap.offline.real_eval import oracle_weights, plain_profile
    from livecap.offline.solve import solve_take
    from transport.llf_csv import read_llf_csv

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--noise", type=float, nargs="+", default=[0.5, 0.2])
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--start", type=float, default=10.0)
    p.add_argument("--occlusion", type=float, default=0.05)
    p.add_argument("--bands", type=int, default=3)
    p.add_argument("--sweeps", type=int, default=1)
    p.add_argument("--files", nargs="+", help="held-out files by name (default: all six)")
    p.add_argument("--mean", choices=["checked", "self", "truth"], default="checked",
                   help="the prior's mean: today's check against the take; the take's own no-prior kalman fit's mean "
                        "(offline, no truth); the take's true mean (a ceiling, not a criterion)")
    p.add_argument("--cov", default="checked",
                   choices=["checked", "self", "pooled", "denoised", "truth", "truthdiag", "em", "mix", "mixem"],
                   help="the prior's covariance: today's; the take's own no-prior kalman fit's (offline, no truth); "
                        "the mean of that and the others' (pooled); the own fit's less its per-frame noise "
                        "noise^2 (B'B)^-1 (denoised); the take's true weights' (a ceiling), its diagonal only "
                        "(truthdiag); by the markers' evidence on the check's frames: EM about the checked mean (em), "
                        "per-performer priors mixed (mix), "
                        "EM from the mixed prior (mixem)")
    p.add_argument("--mix-by", choices=["performer", "file"], default="performer",
                   help="mix: one component per performer of the other files, or per file")
    p.add_argument("--mix-pooled", action="store_true",
                   help="mix: the prior from all other files as one more component")
    p.add_argument("--em-prior", type=float, nargs="+", default=[1.0],
                   help="em: the others' covariance's weight in frames, x the frames the covariance is fitted on; "
                        "several (inf: the others' covariance): chosen per take by the held-out half's evidence")
    p.add_argument("--em-frames", type=int, default=0,
                   help="em / mix: fit on this many of the take's smoothed frames, evenly spread (0: the check's own)")
    p.add_argument("--extend", type=float, nargs="*", default=[],
                   help="strengths added to the grid (also offered to today's criterion): is the grid's end the limit?")
    p.add_argument("--json")
    args = p.parse_args(argv)
    logging.getLogger("livecap").setLevel(logging.ERROR)  # the check's warnings, once per solve

    grid0 = marker_kalman.STRENGTHS
    grid = marker_kalman.STRENGTHS = np.unique(np.concatenate([grid0, args.extend]))
    unit = int(np.argmin(np.abs(grid - 1.0)))  # banded fits run at strength 1, the bands carrying the grid's values
    take_strength, use_support = marker_kalman.take_strength, marker_kalman.MarkerKalmanSolver._use_support
    support, smooth = marker_kalman.MarkerKalmanSolver._support, marker_kalman.smooth_take
    state: dict = {"fixed": None, "scales": None, "chosen": None, "mean": None, "precision": None}
    evidence: dict = {}  # per take: the check's frames, the evidence-based prior (cached: the same for every solve)

    def smoothed_take(targets, valid, settings, r=None):
        out = smooth(targets, valid, settings, r)
        if r is None:
            evidence["smoothed"] = out[:2]
        return out

    def frames_of(targets, valid):
        if not args.em_frames:
            return targets, valid
        x, ok = evidence["smoothed"]
        pick = marker_kalman._spread(len(x), args.em_frames)
        return x[pick].reshape(len(pick), -1), ok[pick]

    def with_em(self, s, prior_cov, targets, valid):
        """The checked prior ``s`` with its covariance by EM from ``prior_cov`` about its mean."""
        if "cov" not in evidence:
            x, ok = frames_of(targets, valid)
            ratio, scores = args.em_prior[0], []
            if len(args.em_prior) > 1:
                ratio, scores = held_out_ratio(self.profile.basis, s.mean, prior_cov, x, ok, self.pose.matrix,
                                               s.noise_var, args.em_prior)
            C, s2, it = evidence_cov(self.profile.basis, s.mean, prior_cov, x, ok, self.pose.matrix, s.noise_var,
                                     min(ratio, 1e9) * len(x))
            evidence.update(cov=C, noise_var=s2, iterations=it, ratio=ratio, scores=scores)
        C = evidence["cov"] + (0 if s.mean_cov is None else s.axes @ s.mean_cov @ s.axes.T)
        lam, axes = np.linalg.eigh(C)
        return type(s)(axes, lam, lam, s.noise_var, s.iterations, s.mean)

    def evidence_support(self, targets, valid, noise_mm, tol=1e-2, outside=np.inf):
        if args.cov not in ("mix", "mixem"):
            s = support(self, targets, valid, noise_mm, tol, outside=outside)
            return with_em(self, s, self.prior_cov, targets, valid) if args.cov == "em" else s
        if "mix" not in evidence:
            x, ok = frames_of(targets, valid)
            base = support(self, targets, valid, noise_mm, tol, outside=outside)
            logp = np.array([log_evidence(self.profile.basis, c.mean, c.cov, x, ok, self.pose.matrix, base.noise_var)
                             for c in state["components"]])
            evidence["mix"] = mixture([c.mean for c in state["components"]], [c.cov for c in state["components"]],
                                      logp)
            evidence["logp"] = logp
        mu, C, _ = evidence["mix"]
        from solvers.prior_support import widen_prior

        s = widen_prior(self.profile.basis, mu, C, targets, valid, self.lower, self.upper, extra=self.pose.matrix,
                        noise_var=noise_mm**2, tol=tol, outside=outside)
        return with_em(self, s, C, targets, valid) if args.cov == "mixem" else s

    def fixed_strength(*a, **k):
        best, err, used = take_strength(*a, **k)
        state["chosen"] = best
        return (best if state["fixed"] is None else state["fixed"]), err, used

    def banded_support(self, s, frames, built=None):
        use_support(self, s, frames, built)
        if state["mean"] is not None:
            self.mean = state["mean"]
        if state["precision"] is not None:
            self.precision = state["precision"]
        if state["scales"] is not None:
            parts, _ = band_precisions(self.profile.basis, self.precision, len(state["scales"]))
            self.precision = sum(c * Pb for c, Pb in zip(state["scales"], parts, strict=True))
        if any(state[k] is not None for k in ("mean", "precision", "scales")):
            self.joint = self.pose.augment(self.profile.basis, self.lower, self.upper, self.mean, self.precision)
            self._fits, self._spreads, self._along = {}, {}, {}
        state["used"] = (self.mean, self.precision)

    files = sorted((_realdata() / "performance").glob("*.csv"))
    rig, layout = _rig("ict")
    out = []
    marker_kalman.take_strength = fixed_strength
    marker_kalman.MarkerKalmanSolver._use_support = banded_support
    marker_kalman.MarkerKalmanSolver._support = evidence_support
    marker_kalman.smooth_take = smoothed_take
    try:
        for noise in args.noise:
            for f in files:
                if args.files and f.stem not in args.files:
                    continue
                t0 = time.perf_counter()
                length = read_llf_csv(f).times[-1]
                start = max(0.0, min(args.start, length - args.seconds))
                ct = curves_take(rig, layout, f, CurveTakeSettings(start=start, seconds=args.seconds, noise_mm=noise,
                                                                  occlusion=args.occlusion))
                oracle = weight_rmse(oracle_weights(ct, rig.lower, rig.upper), ct.weights)
                profile = plain_profile(rig, layout, ct)
                profile.prior = build_prior([o for o in files if o != f], rig.names, rig.lower, rig.upper)
                opts = {"rate": ct.take.rate}
                state["mean"] = state["precision"] = state["scales"] = state["fixed"] = None
                evidence.clear()
                if args.cov in ("mix", "mixem"):
                    from benchmarks.prior_lopo import PERFORMERS

                    group = PERFORMERS if args.mix_by == "performer" else {o.stem: o.stem for o in files}
                    groups = sorted({group[o.stem] for o in files if o != f})
                    state["components"] = [build_prior([o for o in files if o != f and group[o.stem] == g],
                                                       rig.names, rig.lower, rig.upper) for g in groups]
                    if args.mix_pooled:
                        groups.append("pooled")
                        state["components"].append(profile.prior)
                if "self" in (args.mean, args.cov) or args.cov in ("pooled", "denoised"):
                    bare = plain_profile(rig, layout, ct)
                    fit = build_solver("kalman", bare, opts)
                    own = solve_take(ct.take, bare, fit).weights
                if args.mean == "self":
                    state["mean"] = own.mean(0)
                elif args.mean == "truth":
                    state["mean"] = ct.weights.mean(0)
                if args.cov not in ("checked", "em", "mix", "mixem"):
                    C = np.cov((ct.weights if args.cov.startswith("truth") else own).T)
                    if args.cov == "truthdiag":  # which shapes this actor moves and how far, not how they co-move
                        C = np.diag(np.diag(C) + VARIANCE_FLOOR)
                    if args.cov == "pooled":
                        C = 0.5 * (C + profile.prior.cov)
                    elif args.cov == "denoised":
                        C = denoised(C, bare.basis, fit.chosen["noise_mm"])
                    state["precision"] = np.linalg.inv(C + 1e-6 * np.trace(C) / len(C) * np.eye(len(C)))

                def ratio(fixed, scales=None, profile=profile, opts=opts, ct=ct, oracle=oracle):
                    state["fixed"], state["scales"] = fixed, scales
                    W = solve_take(ct.take, profile, build_solver("kalman", profile, opts)).weights
                    return weight_rmse(W, ct.weights) / oracle

                chosen = ratio(None)
                k_chosen = state["chosen"]
                truth_nll = nll(ct.weights, *state["used"])
                scalar = [ratio(k) for k in range(len(grid))]
                k_best = int(np.argmin(scalar))
                _, d = band_precisions(profile.basis, np.linalg.inv(profile.prior.cov), args.bands)
                ks = [k_best] * args.bands
                best = scalar[k_best]
                for _ in range(args.sweeps):
                    for b in range(args.bands):
                        for k in range(len(grid)):
                            if k == ks[b]:
                                continue
                            trial = ks.copy()
                            trial[b] = k
                            r = ratio(unit, [grid[j] for j in trial])
                            if r < best:
                                best, ks = r, trial
                rec = {"noise_mm": noise, "mean": args.mean, "cov": args.cov, "file": f.stem, "oracle_rmse": oracle,
                       "chosen_x": chosen, "truth_nll": truth_nll,
                       "chosen_strength": float(grid[k_chosen]), "scalar_x": scalar,
                       "best_scalar_x": scalar[k_best], "best_scalar": float(grid[k_best]), "bands_x": best,
                       "band_strengths": [float(grid[j]) for j in ks],
                       "d_quantiles": np.quantile(d, [0, 0.25, 0.5, 0.75, 1]).tolist()}
                if args.cov in ("em", "mixem"):
                    rec.update(em_iterations=evidence["iterations"], em_noise_var=evidence["noise_var"],
                               em_ratio=evidence["ratio"], em_scores=evidence["scores"])
                if args.cov in ("mix", "mixem"):
                    rec.update(groups=groups, mix_logp=evidence["logp"].tolist(), mix_r=evidence["mix"][2].tolist())
                out.append(rec)
                print(f"{noise:g} mm {f.stem:32s} chosen {chosen:.3f} ({grid[k_chosen]:.3g})  "
                      f"scalar {scalar[k_best]:.3f} "
                      f"({grid[k_best]:.3g})  bands {best:.3f} {[f'{grid[j]:.3g}' for j in ks]}  "
                      f"[{time.perf_counter() - t0:.0f} s]", flush=True)
    finally:
        marker_kalman.take_strength = take_strength
        marker_kalman.STRENGTHS = grid0
        marker_kalman.MarkerKalmanSolver._use_support = use_support
        marker_kalman.MarkerKalmanSolver._support = support
        marker_kalman.smooth_take = smooth
    for noise in args.noise:
        rows = [r for r in out if r["noise_mm"] == noise]
        print(f"{noise:g} mm mean: chosen {np.mean([r['chosen_x'] for r in rows]):.3f}  scalar "
              f"{np.mean([r['best_scalar_x'] for r in rows]):.3f}  bands {np.mean([r['bands_x'] for r in rows]):.3f}")
    if args.json:
        Path(args.json).write_text(json.dumps({"date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
                                               "loadavg": os.getloadavg(), "args": vars(args), "rows": out},
                                              indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
