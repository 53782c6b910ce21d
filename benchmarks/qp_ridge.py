"""``qp``'s ridge on takes driven by real performances: accuracy and per-frame time beside ``robust``.

Curio et al. 2006 §2.3 fit each frame under positivity constraints alone (``qp``'s default ``ridge=0``). Under
marker noise that problem is ill-conditioned: the noise moves dozens of weights across a bound every frame, which
makes the solve slow (issue 18) and the weights jittery. This suite measures what a Tikhonov term lambda |w|^2
(Lewis et al. 2014 §5.2) does to accuracy and speed on every rig, so that a default is chosen by measurement:

    python -m benchmarks.qp_ridge [--quick] [--rigs ict,demo,makehuman] [--ridges 0,1,3,10,30] [--noise 0.5]

Per Live Link Face CSV in ``$LIVECAP_SHARED/realdata/performance`` (or ``../shared``): a 10 s take of the rig
driven by it (``livecap.demo.curves_take``, 5 % of marker-frames occluded in bursts, the given marker noise), the
plain profile ``livecap realeval`` uses, then every solver streamed frame by frame through the live pipeline
(``livecap.offline.streamed``: causal head pose, no gap filling, as ``livecap run``). Weight RMSE and vertex p95 are
ratios to the true-basis, true-pose oracle (as in ``livecap realeval``); jitter is x the ground truth's; time is
the wall p50 / p99 of ``step`` as the pipeline times it (after its warm-up).
``makehuman`` is the CC0 MakeHuman head with the markers ``livecap rig transfer``
places from the ICT rig (``livecap.transfer.transfer``, ~9 s, as ``livecap rig transfer --target-units cm``) and
``examples/makehuman_arkit.json``.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

from benchmarks.timing import suite_main, table

ROOT = Path(__file__).resolve().parents[1]
MEANS = ("rmse", "rmse_x", "p95_x", "jitter_x", "blink")  # averaged over files in the summary


def _rig(name: str):
    """(rig, layout, ARKit name mapping or None) of ``ict``, ``demo`` or ``makehuman``."""
    from livecap.cli.realeval import _realdata, _rig

    if name != "makehuman":
        return (*_rig(name), None)
    from livecap.core.objfile import read_obj
    from livecap.core.rig import Rig
    from livecap.core.units import to_mm
    from livecap.transfer import transfer
    from transport.arkit import load_mapping

    head = _realdata() / "makehuman-head"
    verts, tris = read_obj(head / "neutral.obj")
    layout = transfer(*_rig("ict"), to_mm(verts, "cm"), tris).layout  # bound to the head's own mesh
    return Rig.load(head), layout, load_mapping(ROOT / "examples" / "makehuman_arkit.json")


def _mean(values: list[float]) -> float:
    """Mean of the finite values (a take without a blink has no blink retention), NaN if none."""
    finite = [v for v in values if np.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


def run(quick: bool = False, rigs=("ict", "demo", "makehuman"), ridges=("0", "1", "3", "10", "30"),
        noise=("0.5",)) -> dict:
    from livecap.cli.realeval import _realdata
    from livecap.demo.curves_take import CurveTakeSettings, curves_take
    from livecap.offline.real_eval import oracle_weights, plain_profile, score
    from livecap.offline.streamed import stream_take
    from transport.llf_csv import read_llf_csv

    files = sorted((_realdata() / "performance").glob("*.csv"))
    if not files:
        raise SystemExit(f"{_realdata() / 'performance'}: no Live Link Face CSVs (set LIVECAP_SHARED)")
    files = files[:2] if quick else files
    seconds = 3.0 if quick else 10.0
    solvers = [("robust", {})] + [("qp", {"ridge": float(r)}) for r in ridges if r]
    rows, load = [], os.getloadavg()[0]
    for rig_name in (r for r in rigs if r):
        rig, layout, mapping = _rig(rig_name)
        for sigma in (float(s) for s in noise if s):
            for f in files:
                length = read_llf_csv(f).times[-1]
                s = CurveTakeSettings(start=max(0.0, min(10.0, length - seconds)), seconds=seconds,
                                      noise_mm=sigma, occlusion=0.05)
                ct = curves_take(rig, layout, f, s, mapping)
                oracle = score("oracle", rig, ct, oracle_weights(ct, rig.lower, rig.upper), 0.0)
                profile = plain_profile(rig, layout, ct)
                for mode, options in solvers:
                    st = stream_take(ct.take, profile, mode, options)  # as `livecap run` feeds it (issue 41.4)
                    r = score(mode, rig, ct, st.weights, 0.0)
                    rows.append({"rig": rig_name, "noise_mm": sigma, "file": f.name, "mode": mode,
                                 "ridge": options.get("ridge"), "rmse": r.rmse, "rmse_x": r.rmse / oracle.rmse,
                                 "p95_x": r.p95_mm / oracle.p95_mm, "jitter_x": r.jitter_x, "blink": r.blink,
                                 "p50_us": st.step_ms["p50_ms"] * 1e3, "p99_us": st.step_ms["p99_ms"] * 1e3})
    summary = []
    for key in dict.fromkeys((r["rig"], r["noise_mm"], r["mode"], r["ridge"]) for r in rows):
        sel = [r for r in rows if (r["rig"], r["noise_mm"], r["mode"], r["ridge"]) == key]
        solver = key[2] if key[3] is None else f"qp ridge={key[3]:g}"
        summary.append({"rig": key[0], "noise_mm": key[1], "solver": solver, "files": len(sel),
                        **{k: _mean([r[k] for r in sel]) for k in MEANS},
                        "p50_us": float(np.median([r["p50_us"] for r in sel])),
                        "p99_us": float(np.median([r["p99_us"] for r in sel]))})
    print(table(summary, ["rig", "noise_mm", "solver", "files", "rmse", "rmse_x", "p95_x", "jitter_x", "blink",
                       "p50_us", "p99_us"],
                f"qp's ridge on real performances ({seconds:g} s takes, 5 % occluded): means over files of weight RMSE "
                f"(and x the oracle), vertex p95 (x the oracle), jitter (x truth) and blink peak retention (solved / "
                f"true peak); step p50 / p99 medians over files; load average {load:.2f} at start, "
                f"{os.getloadavg()[0]:.2f} at end"))
    return {"rows": rows, "summary": summary, "seconds": seconds, "load_start": load,
            "load_end": os.getloadavg()[0]}


if __name__ == "__main__":
    sys.exit(suite_main(run, __doc__, rigs="ict,demo,makehuman", ridges="0,1,3,10,30", noise="0.5"))
