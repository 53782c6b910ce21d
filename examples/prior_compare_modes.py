"""Build an animation prior and compare solver modes against ground truth (livecap's API, docs/api.md).

    python examples/prior_compare_modes.py recordings/demo_take.c3d --rig recordings/demo_rig.npz \
        --neutral recordings/demo_neutral.c3d [--frames 600]

The prior is learned from Live Link Face curves; here, to stay self-contained, from the curves a first
solve of the take writes (in practice: real performances of the actor, ``livecap prior build``). The take
needs ground truth beside it (``<take>.truth.npz``, what ``livecap generate`` writes).
"""

import sys
import tempfile
from pathlib import Path

import numpy as np

import livecap
from livecap.calibration.animation_prior import build_prior
from livecap.demo.performance import GroundTruth


def main(argv: list[str]) -> int:
    take_path, rest = Path(argv[0]), argv[1:]
    opts = dict(zip(rest[::2], rest[1::2], strict=True))
    rig = livecap.load_rig(opts["--rig"])
    layout = livecap.load_layout(opts["--rig"], rig)
    frames = int(opts.get("--frames", 0)) or None
    take = livecap.load_take(take_path).slice(0, frames)
    profile = livecap.calibrate(livecap.load_take(opts["--neutral"]), rig, layout)

    curves = Path(tempfile.mkdtemp()) / "curves.csv"
    livecap.Solver(profile, mode="robust").solve_take(take).to_llf_csv(curves)
    prior = build_prior([curves], rig.names, rig.lower, rig.upper)
    with_prior = livecap.calibrate(livecap.load_take(opts["--neutral"]), rig, layout, prior=prior)

    truth = GroundTruth.load(take_path.with_name(take_path.stem + ".truth.npz"))
    W = truth.weights[: take.n_frames, [truth.names.index(n) for n in rig.names]]
    print(f"{'mode':28s} {'weight RMSE':>11s}")
    for label, prof, mode in (("robust", profile, "robust"), ("qp ridge 0.01", profile, "qp"),
                              ("auto with prior (kalman)", with_prior, "auto")):
        solver = livecap.Solver(prof, mode=mode, **({"ridge": 0.01} if mode == "qp" else {}))
        rmse = float(np.sqrt(np.mean((solver.solve_take(take).values - W) ** 2)))
        print(f"{label:28s} {rmse:11.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
