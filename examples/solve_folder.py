"""Solve every take in a folder from Python and print one line per take (livecap's API, docs/api.md).

    python examples/solve_folder.py TAKES_DIR --rig recordings/demo_rig.npz [--profile actor.npz] [--out DIR]

Without --profile each take is calibrated on its own first second, as ``livecap solve`` does.
"""

import sys
from pathlib import Path

import numpy as np

import livecap


def main(argv: list[str]) -> int:
    folder, rest = Path(argv[0]), argv[1:]
    opts = dict(zip(rest[::2], rest[1::2], strict=True))
    rig = opts["--rig"]
    profile = livecap.load_profile(opts["--profile"]) if "--profile" in opts else None
    out = Path(opts["--out"]) if "--out" in opts else None
    print(f"{'take':24s} {'frames':>6s} {'residual p50 mm':>15s} {'peak shape':>18s}")
    for path in sorted(p for p in folder.iterdir() if p.suffix.lower() in (".c3d", ".trc", ".csv")):
        weights = livecap.solve(path, rig=rig, profile=profile)
        peak = weights.names[int(np.argmax(weights.values.max(axis=0)))]
        print(f"{path.stem:24s} {len(weights):6d} {np.nanmedian(weights.residual):15.3f} {peak:>18s}")
        if out is not None:
            out.mkdir(parents=True, exist_ok=True)
            weights.to_csv(out / f"{path.stem}.csv")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
