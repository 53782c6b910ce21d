"""Which retargeting path serves which rig (issue 40 item 2): vertices against the ICT face driven by the same weights.

The reference is the ICT face (ARKit-like shapes) driven by a real Live Link Face performance, carried onto
the target's own topology and identity by rig transfer (livecap.transfer: landmarks, deformable model,
deformation transfer of every ICT shape, dense correspondence; Xiang et al. 2008, Sumner & Popovic 2004):
the transferred rig has the target's neutral, so a path's vertices and the reference's differ only by
their displacements. Paths: by name, by the mapping file (examples/makehuman_arkit.json for the MakeHuman
head) and by expression transfer (livecap.retarget.ExpressionTransfer) with the sites from rig transfer or
bound by ICP. Reported per path: RMS over the face's vertices of the displacement error (mm), mean over
frames and its p95, and that mean relative to the reference's own RMS displacement (1.0 = no better than
holding the neutral face). The ICT rig itself is a target too (its reference is itself).

    python -m benchmarks.iphone_retarget [--seconds 20] [--csv S07-001.csv apfel.csv]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from livecap.core.markers import MarkerLayout
from livecap.core.rig import Rig
from livecap.retarget import ByName, ExpressionTransfer, TransferSettings
from tests.conftest import ROOT, SHARED
from transport.arkit import load_mapping
from transport.llf_csv import read_llf_csv

ICT = SHARED / "realdata" / "ict-face"
MH = SHARED / "realdata" / "makehuman-head"
PERF = SHARED / "realdata" / "performance"


def _error(V: np.ndarray, ref: np.ndarray, face: np.ndarray, rest: np.ndarray) -> dict:
    rms = np.sqrt(np.mean(np.sum((V[:, face] - ref[:, face]) ** 2, axis=2), axis=1))
    own = np.sqrt(np.mean(np.sum((ref[:, face] - rest[face]) ** 2, axis=2), axis=1))
    return {"rms_mm": float(rms.mean()), "p95_mm": float(np.percentile(rms, 95)),
            "relative": float(rms.mean() / max(own.mean(), 1e-12)), "reference_rms_mm": float(own.mean())}


def oracle(rig: Rig, reference: np.ndarray, face: np.ndarray) -> np.ndarray:
    """The rig's best weights for each frame over every face vertex (bounded least squares): its floor."""
    from scipy.optimize import lsq_linear

    B = rig.deltas[:, face].reshape(rig.n_shapes, -1).T
    d = (reference[:, face] - rig.neutral[face]).reshape(len(reference), -1)
    return np.array([lsq_linear(B, x, bounds=(rig.lower, rig.upper)).x for x in d])


def _timed(fn, arkit):
    t0 = time.perf_counter()
    W = fn(arkit)
    return W, (time.perf_counter() - t0) / len(arkit) * 1e3


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--csv", nargs="+", default=["S07-001.csv", "apfel.csv"])
    ap.add_argument("--seconds", type=float, default=20.0, help="seconds of each CSV (from its start)")
    ap.add_argument("--rate", type=float, default=30.0)
    ap.add_argument("--ridge", type=float, nargs="+", default=[TransferSettings.ridge])
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "iphone-retarget.json"))
    args = ap.parse_args(argv)
    from livecap.transfer import transfer

    ict = Rig.load(ICT)
    ict_layout = MarkerLayout.load(ICT / "markers.json", ict)
    mh = Rig.load(MH)
    t0 = time.perf_counter()
    res = transfer(ict, ict_layout, mh.neutral, mh.triangles)
    transfer_s = time.perf_counter() - t0
    ref_rig, mh_sites = res.rig, res.layout
    face = np.flatnonzero(np.abs(ref_rig.deltas).max(axis=(0, 2)) > 1e-6)
    mapping = load_mapping(ROOT / "examples" / "makehuman_arkit.json")
    rows = []
    for name in args.csv:
        curves = read_llf_csv(PERF / name)
        arkit = curves.resample(args.rate)[0][: int(args.seconds * args.rate)]
        ref_ict = ict.evaluate(ByName(ict).apply(arkit))
        ref_mh = ref_rig.evaluate(ByName(ref_rig).apply(arkit))
        ict_face = np.arange(ict.n_vertices)

        def add(rig_name, path, fn, rig, ref, face_idx, rest, data=name, arkit=arkit):
            try:
                W, ms = _timed(fn, arkit)
            except ValueError as exc:
                rows.append({"csv": data, "rig": rig_name, "path": path, "error": str(exc)})
                print(f"{data} {rig_name:10s} {path:28s} {exc}")
                return
            e = _error(rig.evaluate(W), ref, face_idx, rest)
            rows.append({"csv": data, "rig": rig_name, "path": path, "ms_per_frame": ms, **e})
            print(f"{data} {rig_name:10s} {path:28s} {e['rms_mm']:.3f} mm (p95 {e['p95_mm']:.3f}) "
                  f"relative {e['relative']:.3f}  {ms:.3f} ms/frame", flush=True)

        add("ict", "name", lambda a: ByName(ict).apply(a), ict, ref_ict, ict_face, ict.neutral)
        for r in args.ridge:
            s = TransferSettings(ridge=r)
            add("ict", f"transfer (ridge {r:g})", lambda a, s=s: ExpressionTransfer(ict, ict_layout, ict, ict_layout,
                                                                                      s).apply(a),
                ict, ref_ict, ict_face, ict.neutral)
        add("makehuman", "neutral (nothing)", lambda a: np.zeros((len(a), mh.n_shapes)), mh, ref_mh, face, mh.neutral)
        add("makehuman", "best weights (oracle)", lambda a, ref=ref_mh: oracle(mh, ref, face), mh, ref_mh, face,
            mh.neutral)
        add("makehuman", "name", lambda a: ByName(mh, where="makehuman").apply(a), mh, ref_mh, face, mh.neutral)
        add("makehuman", "map", lambda a: ByName(mh, mapping).apply(a), mh, ref_mh, face, mh.neutral)
        for r in args.ridge:
            s = TransferSettings(ridge=r)
            add("makehuman", f"transfer, sites by rig transfer (ridge {r:g})",
                lambda a, s=s: ExpressionTransfer(ict, ict_layout, mh, mh_sites, s).apply(a),
                mh, ref_mh, face, mh.neutral)
            add("makehuman", f"transfer, sites bound (ridge {r:g})",
                lambda a, s=s: ExpressionTransfer(ict, ict_layout, mh, None, s).apply(a),
                mh, ref_mh, face, mh.neutral)
    meta = {"date": datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"), "load": os.getloadavg(),
            "machine": "2-core AMD EPYC VM (shared)", "rate": args.rate, "seconds": args.seconds,
            "rig_transfer_s": transfer_s, "face_vertices": int(len(face))}
    Path(args.out).write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    print(json.dumps(meta))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
