"""Where the calibrated basis's eye-shape bias comes from (issue 41): the basis against the true actor's, and what each
shape's basis error costs a solve.

Per held-out ICT take (``livecap realeval``'s: six real performances, 10 s from 10 s in, 5 % occlusion, the prior from
the other five files unless ``--no-prior``), the calibrated profile is compared with the generator's truth, which the
oracle uses:

- **the basis, per shape**: the calibrated column against the true one at the markers (the true actor basis rotated
  into the profile's frame by the rigid fit of the true neutral onto the calibrated one): angle (degrees), scale
  (least-squares ``<b_cal, b_true> / |b_true|^2``) and relative error, for each calibration step replaced by its
  exact counterpart: ``rbf`` (today: the RBF warp fitted to the estimated neutral), ``rbf@true neutral`` (the same
  warp fitted to the noise-free actor neutral: what the neutral's noise costs the warp), ``true warp`` (the
  generator's warp, sculpts warped as calibration does: equals the truth to rounding);
- **counterfactual solves** (``auto`` as ``realeval`` resolves it, offline as ``livecap solve`` and with ``--stream``
  streamed as ``livecap run``): the calibrated profile, the true basis, the true neutral, both, the true head pose
  (offline), and the calibrated basis with one shape pair's columns set to the true ones, as weight RMSE over the
  oracle's; with ``--kernels`` also the basis from other interpolants of the estimated neutral (``PolyharmonicWarp``)
  and from the RBF warp's Jacobian (``linearised_basis``), prototypes of calibration changes.

``--seed`` / ``--draw``: the base seed and draw index of the takes' noise, occlusion and neutral noise, one draw per
file as ``livecap realeval`` draws it (``curves_take.take_seed``; before 2026-12-06 every take used seed 1, so five
of the six files shared one draw); ``--neutral-seconds`` lengthens the neutral take.

    python -m benchmarks.basis_bias --noise 0.5 0.2 [--no-prior] [--stream] [--seed S] [--draw D] [--kernels]
        [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

EYE_PAIRS = ("eyeLookUp", "eyeWide", "eyeSquint", "eyeLookOut", "eyeLookIn", "eyeLookDown", "eyeBlink")


def column_errors(B: np.ndarray, T: np.ndarray, names: list[str]) -> dict[str, dict[str, float]]:
    """Per shape: angle (deg), scale and relative error of the columns of ``B`` (3n x m) against ``T``."""
    out = {}
    for k, name in enumerate(names):
        a, b = B[:, k], T[:, k]
        nb = float(np.linalg.norm(b))
        if nb < 1e-9:
            continue
        cos = float(a @ b / max(np.linalg.norm(a) * nb, 1e-300))
        out[name] = {"angle": float(np.degrees(np.arccos(np.clip(cos, -1, 1)))), "scale": float(a @ b / nb ** 2),
                     "rel": float(np.linalg.norm(a - b) / nb)}
    return out


def true_in_profile(ct, profile) -> tuple[np.ndarray, np.ndarray]:
    """The true actor neutral (n x 3) and basis (3n x m) in the calibrated profile's frame."""
    from solvers.rigid import kabsch

    R, t = kabsch(ct.actor_neutral, profile.source_neutral)
    neutral = ct.actor_neutral @ R.T + t
    basis = np.einsum("ij,snj->sni", R, ct.actor_basis).reshape(len(ct.names), -1).T
    return neutral, basis


class TruePose:
    """A stabiliser that returns the generator's head pose, expressed in the profile's frame."""

    def __init__(self, ct, profile) -> None:
        from scipy.spatial.transform import Rotation

        from solvers.rigid import kabsch

        Rk, tk = kabsch(ct.actor_neutral, profile.source_neutral)  # head frame -> profile frame
        Rh = Rotation.from_quat(ct.head_rotation).as_matrix()
        self.R = Rh @ Rk.T  # raw = R local + t
        self.t = ct.head_translation - np.einsum("tij,j->ti", self.R, tk)

    def stabilise(self, positions: np.ndarray, valid: np.ndarray):
        local = (np.asarray(positions, np.float64) - self.t[:, None, :]) @ self.R
        return np.where(np.asarray(valid, bool)[..., None], local, 0.0), self.R, self.t


class PolyharmonicWarp:
    """Prototype (not calibration's): ``sum_i w_i |x - c_i|^power + q(x)``, ``q`` affine or quadratic, interpolating
    exactly. ``power`` 3 is the smoother triharmonic kernel; a quadratic ``q`` reproduces any quadratic warp exactly,
    which is the generator's actor family (``performance.actor_warp``), so it favours that actor by construction."""

    def __init__(self, centres: np.ndarray, targets: np.ndarray, power: int = 1, quadratic: bool = False) -> None:
        self.mu = centres.mean(0)
        self.s = float(np.sqrt(np.mean(np.sum((centres - self.mu) ** 2, 1))))
        self.cn, self.power, self.quadratic = (centres - self.mu) / self.s, power, quadratic
        n, P = len(centres), self._poly(self.cn)
        M = np.zeros((n + P.shape[1], n + P.shape[1]))
        M[:n, :n], M[:n, n:], M[n:, :n] = self._kernel(self.cn), P, P.T
        sol = np.linalg.solve(M, np.vstack([targets, np.zeros((P.shape[1], 3))]))
        self.w, self.a = sol[:n], sol[n:]

    def _poly(self, x: np.ndarray) -> np.ndarray:
        cols = [x, np.ones(x.shape[:-1] + (1,))]
        if self.quadratic:
            i, j = np.triu_indices(3)
            cols.append(x[..., i] * x[..., j])
        return np.concatenate(cols, -1)

    def _kernel(self, x: np.ndarray) -> np.ndarray:
        return np.linalg.norm(x[..., None, :] - self.cn, axis=-1) ** self.power

    def __call__(self, p: np.ndarray) -> np.ndarray:
        x = (np.asarray(p, np.float64) - self.mu) / self.s
        return self._kernel(x) @ self.w + self._poly(x) @ self.a


def linearised_basis(sites_rig, warp) -> np.ndarray:
    """The sculpts' deltas through the RBF warp's Jacobian at each site (3n x m), the centre's own cone (its kernel
    has no derivative there) left out: the linearised transfer, against calibration's ``warp(x + delta) - warp(x)``."""
    cn = (warp.centres - warp.mu) / warp.scale
    diff = cn[:, None, :] - cn[None, :, :]  # site i minus centre j
    dist = np.linalg.norm(diff, axis=2)
    np.fill_diagonal(dist, np.inf)
    J = (np.einsum("ija,jc->ica", diff / dist[..., None], warp.weights)
         + warp.affine[:3].T[None]) / warp.scale  # n x 3 x 3: d(out c) / d(in a) as [i, c, a]
    return np.einsum("ica,kia->kic", J, sites_rig.deltas).reshape(len(sites_rig.deltas), -1).T


KERNELS = {"warp r^3": (3, False), "warp |r| + quadratic": (1, True), "warp r^3 + quadratic": (3, True)}


def warp_variants(rig, layout, ct, profile) -> dict[str, np.ndarray]:
    """The basis each calibration step gives when one input is replaced by the truth (see the module doc)."""
    from livecap.calibration.profile import fit_warp
    from livecap.calibration.warp import warp_rig
    from livecap.demo.curves_take import _centred_warp
    from solvers.rigid import kabsch

    sites_rig = layout.marker_rig(rig)
    sites = sites_rig.neutral
    true_neutral, _ = true_in_profile(ct, profile)
    out = {}
    d = fit_warp("rbf", sites, true_neutral)
    out["rbf@true neutral"] = warp_rig(sites_rig, d).deltas.reshape(rig.n_shapes, -1).T
    gen = _centred_warp(7, sites.mean(0))  # the generator's actor warp (CurveTakeSettings.actor_seed)
    R, t = kabsch(gen(sites), profile.source_neutral)
    out["true warp"] = warp_rig(sites_rig, lambda p: gen(p) @ R.T + t).deltas.reshape(rig.n_shapes, -1).T
    return out


def solve(ct, profile, opts: dict, stream: bool, stabiliser=None) -> dict[str, np.ndarray]:
    """``auto``'s weights offline (and streamed); ``stabiliser``: the head pose from another neutral (offline only)."""
    from livecap.modes.registry import build_solver, resolve_mode
    from livecap.offline.solve import solve_take
    from livecap.offline.streamed import stream_take

    mode = resolve_mode("auto", profile)
    out = {"offline": solve_take(ct.take, profile, build_solver(mode, profile, opts), stabiliser=stabiliser).weights}
    if stream and stabiliser is None:
        out["stream"] = stream_take(ct.take, profile, mode, opts).weights
    return out


def main(argv: list[str] | None = None) -> int:
    from livecap.calibration.animation_prior import build_prior
    from livecap.cli.realeval import _realdata, _rig
    from livecap.demo.curves_take import CurveTakeSettings, curves_take, take_seed
    from livecap.offline.real_eval import oracle_weights, plain_profile
    from transport.llf_csv import read_llf_csv

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--noise", type=float, nargs="+", default=[0.5, 0.2])
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--files", nargs="+")
    p.add_argument("--no-prior", action="store_true")
    p.add_argument("--stream", action="store_true", help="streamed solves too (slower)")
    p.add_argument("--pairs", nargs="*", default=list(EYE_PAIRS), help="shape pairs (_L/_R) set true one at a time")
    p.add_argument("--seed", type=int, default=1, help="base seed of the takes' draws (1: realeval's)")
    p.add_argument("--draw", type=int, default=0, help="the draw index (realeval --draws N runs 0..N-1; default 0)")
    p.add_argument("--neutral-seconds", type=float, default=2.0, help="the neutral take's length (2: realeval's)")
    p.add_argument("--kernels", action="store_true", help="the basis from other interpolating warps of the "
                   "estimated neutral too (PolyharmonicWarp)")
    p.add_argument("--json")
    args = p.parse_args(argv)
    rig, layout = _rig("ict")
    names = list(rig.names)
    files = sorted((_realdata() / "performance").glob("*.csv"))
    out = []
    for noise in args.noise:
        for f in files:
            if args.files and f.stem not in args.files:
                continue
            t0 = time.perf_counter()
            start = max(0.0, min(10.0, read_llf_csv(f).times[-1] - args.seconds))
            seed = take_seed(f, args.seed, args.draw)
            ct = curves_take(rig, layout, f, CurveTakeSettings(start=start, seconds=args.seconds, noise_mm=noise,
                                                                      seed=seed,
                                                                      neutral_seconds=args.neutral_seconds))
            profile = plain_profile(rig, layout, ct)
            profile.prior = None if args.no_prior else build_prior([o for o in files if o != f], rig.names,
                                                                   rig.lower, rig.upper)
            oracle = float(np.sqrt(np.mean((oracle_weights(ct, rig.lower, rig.upper) - ct.weights) ** 2)))
            true_neutral, true_basis = true_in_profile(ct, profile)
            bases = {"rbf": profile.basis, **warp_variants(rig, layout, ct, profile)}
            cols = {k: column_errors(B, true_basis, names) for k, B in bases.items()}
            variants = {"calibrated": profile, "true basis": replace(profile, basis=true_basis),
                        "true neutral": replace(profile, source_neutral=true_neutral),
                        "true both": replace(profile, basis=true_basis, source_neutral=true_neutral),
                        "rbf@true neutral": replace(profile, basis=bases["rbf@true neutral"]),
                        "true neutral, rbf@true neutral": replace(profile, basis=bases["rbf@true neutral"],
                                                                  source_neutral=true_neutral)}
            if args.kernels:
                from livecap.calibration.warp import warp_rig

                sites_rig = layout.marker_rig(rig)
                for label, (power, quad) in KERNELS.items():
                    d = PolyharmonicWarp(sites_rig.neutral, profile.source_neutral, power, quad)
                    bases[label] = warp_rig(sites_rig, d).deltas.reshape(rig.n_shapes, -1).T
                    variants[label] = replace(profile, basis=bases[label])
                bases["rbf, linearised"] = linearised_basis(sites_rig, profile.warp)
                variants["rbf, linearised"] = replace(profile, basis=bases["rbf, linearised"])
                cols = {k: column_errors(B, true_basis, names) for k, B in bases.items()}
            for pair in args.pairs:
                idx = [names.index(n) for n in (f"{pair}_L", f"{pair}_R", pair) if n in names]
                B = profile.basis.copy()
                B[:, idx] = true_basis[:, idx]
                variants[f"true {pair}"] = replace(profile, basis=B)
            opts = {"rate": ct.take.rate}
            rec = {"noise_mm": noise, "file": f.stem, "seed": seed, "oracle": oracle, "columns": cols,
                   "neutral_err_mm": float(np.sqrt(np.mean(np.sum((profile.source_neutral - true_neutral) ** 2, 1)))),
                   "solves": {}}
            variants["true neutral, pose from calibrated"] = (replace(profile, source_neutral=true_neutral), profile)
            variants["pose from true neutral"] = (profile, replace(profile, source_neutral=true_neutral))
            variants["true pose"] = (profile, TruePose(ct, profile))
            variants["true pose, neutral, basis"] = (replace(profile, basis=true_basis, source_neutral=true_neutral),
                                                     TruePose(ct, profile))
            for label, prof in variants.items():
                prof, stab = prof if isinstance(prof, tuple) else (prof, None)
                stab = stab.stabiliser() if hasattr(stab, "stabiliser") else stab
                for path, W in solve(ct, prof, opts, args.stream, stab).items():
                    bias = (W - ct.weights).mean(0)
                    rec["solves"][f"{label} {path}"] = {
                        "rmse_x": float(np.sqrt(np.mean((W - ct.weights) ** 2))) / oracle,
                        "bias": dict(zip(names, bias.tolist(), strict=True))}
            out.append(rec)
            print(f"{noise:g} {f.stem[:12]:12s} [{time.perf_counter() - t0:.0f} s] neutral err "
                  f"{rec['neutral_err_mm']:.3f} mm; " + "  ".join(
                      f"{k} {v['rmse_x']:.3f}" for k, v in rec["solves"].items()), flush=True)
    mean = {}
    for rec in out:
        for k, v in rec["solves"].items():
            mean.setdefault((rec["noise_mm"], k), []).append(v["rmse_x"])
    for (noise, k), v in mean.items():
        print(f"{noise:g} mm {k:28s} {np.mean(v):.3f}")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"machine": platform.node(), "date": time.strftime("%Y-%m-%d %H:%M"),
                                               "load": Path("/proc/loadavg").read_text().split()[:3],
                                               "argv": sys.argv[1:] if argv is None else argv, "rows": out}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
