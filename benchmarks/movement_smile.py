"""Where ``--mode movement`` loses the right smile on the AnimFace cheek take (issue 35).

Per mode (auto, movement) on an AnimFace take bound to ICT (as ``benchmarks.realcapture``): the smile-corner
correlations (one-sided, ``livecap.offline.plausibility``) of the published weights and of the same solve with the
evidence gate (``livecap.modes.quiet.EvidenceGate``) off, the frames where the corner is > 3 mm above neutral but
mouthSmile < 0.1, the gate's mean factor there, and the shapes that carry the corner's rise. For movement, on chosen
frames: the solve against the per-frame bounded fit with the same position weights and L1 term (its steady state:
Seol's velocity term is zero on a still pose), the same fit without the L1 term, and without the misfit weights.
The streamed figures likewise (``livecap.offline.streamed.stream_take``, the gate off by replacing its call).

    python -m benchmarks.movement_smile [--take CheeksMoCap] [--frames 200,420,450,500]
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.optimize import minimize

from benchmarks.realcapture import SIGNALS


def setup(name: str):
    """The take and its calibrated, tuned profile, exactly as ``benchmarks.realcapture.run_take`` makes them."""
    from livecap.calibration.profile import calibrate, estimate_neutral
    from livecap.cli.realeval import _realdata
    from livecap.core.markers import MarkerLayout
    from livecap.core.rig import Rig
    from livecap.offline.setup import tune_on_take
    from livecap.transfer.bind import bind_capture
    from transport.takefile import read_take

    ict = _realdata() / "ict-face"
    take = read_take(_realdata() / "capture-animface" / f"{name}.c3d")
    rig = Rig.load(ict)
    layout = bind_capture(take, rig, MarkerLayout.load(ict / "markers.json", rig)).layout(rig)
    second = int(round(take.rate))
    profile = calibrate(rig, layout, estimate_neutral(take.select(layout.labels), layout.stable, second))
    tune_on_take(profile, take)
    return take, profile


def per_frame_fit(B, rows, beta, mu, lo, hi, s):
    """argmin beta |diag(rows)^(1/2) (B w - s)|^2 + mu.w inside the limits: the movement solve on a still pose."""
    def f(w):
        r = B @ w - s
        return beta * np.sum(rows * r**2) + mu @ w, 2.0 * beta * B.T @ (rows * r) + mu

    return minimize(f, np.zeros(B.shape[1]), jac=True, method="L-BFGS-B", bounds=list(zip(lo, hi, strict=True)),
                    options={"maxiter": 5000, "ftol": 1e-14, "gtol": 1e-10}).x


def main(argv: list[str] | None = None) -> int:
    from livecap.modes.registry import build_solver
    from livecap.offline import plausibility as pl
    from livecap.offline.solve import solve_take

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--take", default="CheeksMoCap")
    p.add_argument("--frames", default="200,420,450,500", help="frames to compare with the per-frame fit")
    args = p.parse_args(argv)
    take, profile = setup(args.take)
    names, labels = list(profile.names), list(profile.labels)
    smiles = [s for s in SIGNALS if s.kind == "rise" and s.shape.startswith("mouthSmile")]
    n_basis = profile.basis.reshape(len(labels), 3, -1)
    for mode in ("auto", "movement"):
        solver = build_solver(mode, profile, {})
        solved = solve_take(take, profile, solver)
        Y, V, W = solved.targets, solved.valid, solved.weights
        gate, solver.gate = solver.gate, None
        U = solver.solve(Y, V)  # the same solve, the gate off
        solver.gate = gate
        gated = pl.signal_correlations(smiles, names, W, labels, Y, profile.source_neutral)
        open_ = pl.signal_correlations(smiles, names, U, labels, Y, profile.source_neutral)
        print(f"{args.take} {mode} ({type(solver.inner).__name__}):")
        for sig, key in zip(smiles, gated, strict=True):
            j, i = names.index(sig.shape), labels.index(sig.markers[0])
            up = Y[:, i, 1] > 3.0
            factor = W[up, j].sum() / max(U[up, j].sum(), 1e-12)
            carry = U[up] * n_basis[i, 1][None]
            top = np.argsort(-carry.mean(axis=0))[:3]
            print(f"   {sig.shape}: r {gated[key]:.3f} (gate off {open_[key]:.3f}); {up.sum()} frames corner > 3 mm: "
                  f"weight < 0.1 on {(W[up, j] < 0.1).sum()} (gate off {(U[up, j] < 0.1).sum()}), gate keeps "
                  f"{factor:.2f} of it; corner rise {Y[up, i, 1].mean():.1f} mm carried by "
                  + ", ".join(f"{names[k]} {carry[:, k].mean():.1f}" for k in top))
        from livecap.modes.quiet import EvidenceGate
        from livecap.offline.streamed import stream_take

        streamed = stream_take(take, profile, mode).weights
        call, EvidenceGate.__call__ = EvidenceGate.__call__, lambda self, W, targets, valid: W
        try:
            streamed_open = stream_take(take, profile, mode).weights
        finally:
            EvidenceGate.__call__ = call
        st = pl.signal_correlations(smiles, names, streamed, labels, Y, profile.source_neutral)
        st_open = pl.signal_correlations(smiles, names, streamed_open, labels, Y, profile.source_neutral)
        print("   streamed: " + "; ".join(f"{sig.shape} r {st[k]:.3f} (gate off {st_open[k]:.3f})"
                                        for sig, k in zip(smiles, st, strict=True)))
        if mode != "movement":
            continue
        robust = solver.inner
        keep = [names[k] for k in solver.keep]
        blocks = robust.inner.blocks
        B, rows, beta, mu = blocks.basis, blocks.row_weights, blocks.beta, robust.mu
        S = robust.smooth(Y, V).reshape(len(Y), -1)
        R, C = keep.index("mouthSmile_R"), keep.index("cheekSquint_R")
        for f in (int(x) for x in args.frames.split(",")):
            u = U[f, solver.keep]
            fits = {"per-frame fit": per_frame_fit(B, rows, beta, mu, robust.lower, robust.upper, S[f]),
                    "no L1": per_frame_fit(B, rows, beta, 0 * mu, robust.lower, robust.upper, S[f]),
                    "no misfit weights": per_frame_fit(B, np.ones_like(rows), beta, mu, robust.lower, robust.upper,
                                                       S[f])}
            print(f"   frame {f}: solve smile_R {u[R]:.2f} cheekSquint_R {u[C]:.2f}; "
                  + "; ".join(f"{k} {w[R]:.2f} / {w[C]:.2f}" for k, w in fits.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
