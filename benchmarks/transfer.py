"""Rig transfer (Xiang et al. 2008): timing on ~10,000-vertex faces, landmark accuracy, solve agreement.

    python -m benchmarks.transfer [--quick] [--json OUT.json]

* demo -> ICT (9,409 vertices) and ICT -> demo at 10,152 vertices: seconds per stage;
* landmark detection demo -> ICT against ICT's own markers (labels matched through
  livecap.transfer.labels), per landmark, in % of ICT's eye width (Xiang Fig. 5's unit);
* landmark detection ICT -> ICT warped (livecap.demo.performance.actor_warp), moved and
  decimated to half its triangles (ground truth known), for r_d = 6 % (the paper) and 50 %;
* solving: demo rig (seed 0) transferred onto another demo face (seed 3, other resolution);
  a take performed by that face's own rig is solved with its own rig and with the transferred
  one: weight RMSE of each against the truth and between the two.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.timing import suite_main
from livecap.transfer import TransferOptions, transfer
from livecap.transfer.labels import landmark_distances
from livecap.transfer.landmarks import eye_width

ICT = Path(__file__).resolve().parents[1].parent / "shared" / "realdata" / "ict-face"


def _ict():
    from livecap.markers import MarkerLayout
    from livecap.rig import Rig

    rig = Rig.load(ICT)
    return rig, MarkerLayout.load(ICT / "markers.json", rig)


def landmark_report(result, generic_layout, reference_rig, reference_layout) -> dict:
    """Per-landmark distances (mm and % of the reference's eye width) of detected vs reference markers."""
    w_ref, _ = eye_width(reference_layout, reference_rig.neutral)
    ref_pts = reference_layout.sampling_matrix(reference_rig.n_vertices) @ reference_rig.neutral
    rows = landmark_distances(generic_layout.labels, result.landmarks.points, reference_layout.labels, ref_pts)
    pct = np.array([d / w_ref * 100 for _, _, d in rows])
    return {"eye_width_mm": w_ref, "rows": [(a, b, d, d / w_ref * 100) for a, b, d in rows],
            "within_8pct": int((pct < 8).sum()), "n": len(rows), "median_pct": float(np.median(pct))}


def warped_remeshed(rig, layout):
    """A face with a known answer: ``rig`` warped to other proportions, moved, decimated to half
    its triangles; returns its vertices, triangles and where ``layout``'s markers truly are."""
    import igl
    from scipy.spatial.transform import Rotation

    from livecap.demo.performance import actor_warp

    warp = actor_warp(np.random.default_rng(7))
    R = Rotation.from_rotvec([0.1, 0.15, 0.05]).as_matrix()

    def move(p):
        return warp(p) @ R.T + np.array([5.0, -20.0, 12.0])

    V, F, _, _ = igl.decimate(move(rig.neutral), rig.triangles, len(rig.triangles) // 2)
    return V, F, move(layout.sampling_matrix(rig.n_vertices) @ rig.neutral)


def warped_ict_accuracy(radius_fraction) -> dict:
    rig, layout = _ict()
    V, F, truth = warped_remeshed(rig, layout)
    res = transfer(rig, layout, V, F, TransferOptions(radius_fraction=radius_fraction))
    err = np.linalg.norm(res.landmarks.points - truth, axis=1) / res.eye_width * 100
    return {"radius_fraction": radius_fraction, "within_8pct": float((err < 8).mean()),
            "median_pct": float(np.median(err)), "seconds": float(sum(res.seconds.values()))}


def solve_agreement(seconds: float = 20.0, clean: bool = False) -> dict:
    """Weight RMSE: a take of face B solved with B's own rig vs with the demo rig transferred onto B."""
    from livecap.calibration import calibrate, estimate_neutral
    from livecap.demo.face import demo_rig
    from livecap.demo.performance import PerformanceSettings, perform
    from livecap.metrics import weight_rmse
    from livecap.modes import build_solver
    from livecap.solve import solve_take

    generic, generic_layout = demo_rig(0)
    own, own_layout = demo_rig(3, resolution=(56, 50))
    t0 = time.perf_counter()
    res = transfer(generic, generic_layout, own.neutral, own.triangles)
    elapsed = time.perf_counter() - t0
    settings = PerformanceSettings(seconds=seconds)
    if clean:  # no noise, occlusion or poses beyond the limits: only the rigs differ
        settings = PerformanceSettings(seconds=seconds, noise_mm=0.0, occlusion=0.0, beyond_limits=False,
                                       stable_dropout=0.0)
    perf = perform(own, own_layout, settings)
    weights = {}
    for name, rig, layout in (("own", own, own_layout), ("transferred", res.rig, res.layout)):
        take = perf.take.select(layout.labels)
        profile = calibrate(rig, layout, estimate_neutral(take, layout.stable, int(take.rate)))
        solved = solve_take(take, profile, build_solver("lsq", profile))
        weights[name] = solved.weights[:, [rig.names.index(n) for n in perf.names]]
    return {"transfer_seconds": elapsed, "frames": len(perf.weights),
            "rmse_own_vs_truth": weight_rmse(weights["own"], perf.weights),
            "rmse_transferred_vs_truth": weight_rmse(weights["transferred"], perf.weights),
            "rmse_transferred_vs_own": weight_rmse(weights["transferred"], weights["own"])}


def run(quick: bool = False) -> dict:
    from livecap.demo.face import demo_rig

    results: dict = {"machine": "shared 2-core VM (other jobs running)"}
    if not (ICT / "neutral.obj").exists():
        results["skipped"] = f"ICT rig not found at {ICT}"
        return results
    ict, ict_layout = _ict()
    demo, demo_layout = demo_rig(0)
    res = transfer(demo, demo_layout, ict.neutral, ict.triangles)
    results["demo->ict"] = {"target_vertices": ict.n_vertices, "seconds": res.seconds,
                            "total_seconds": float(sum(res.seconds.values())),
                            "landmarks": landmark_report(res, demo_layout, ict, ict_layout)}
    if not quick:
        big, big_layout = demo_rig(0, resolution=(108, 94))
        res2 = transfer(ict, ict_layout, big.neutral, big.triangles)
        results["ict->demo10k"] = {"target_vertices": big.n_vertices, "seconds": res2.seconds,
                                   "total_seconds": float(sum(res2.seconds.values()))}
        results["warped-ict"] = [warped_ict_accuracy(0.06), warped_ict_accuracy(0.5)]
    results["solve"] = solve_agreement(5.0 if quick else 20.0)
    results["solve_clean"] = solve_agreement(5.0 if quick else 20.0, clean=True)
    print_table(results)
    return results


def print_table(results: dict) -> None:
    print(f"rig transfer benchmark ({results['machine']})")
    for key in ("demo->ict", "ict->demo10k"):
        if key in results:
            r = results[key]
            stages = ", ".join(f"{k} {v:.2f}" for k, v in r["seconds"].items())
            print(f"{key:14s} {r['target_vertices']:6d} vertices  total {r['total_seconds']:6.2f} s  ({stages})")
    if "demo->ict" in results:
        lm = results["demo->ict"]["landmarks"]
        print(f"landmarks demo -> ICT (ICT eye width {lm['eye_width_mm']:.1f} mm): "
              f"{lm['within_8pct']}/{lm['n']} within 8 %, median {lm['median_pct']:.1f} %")
        for a, b, d, p in lm["rows"]:
            print(f"  {a:10s} -> {b:9s} {d:6.2f} mm  {p:6.1f} %")
    for w in results.get("warped-ict", []):
        print(f"landmarks ICT -> warped ICT, r_d = {w['radius_fraction']:g} eye widths: "
              f"{w['within_8pct'] * 100:.0f} % within 8 %, median {w['median_pct']:.1f} % ({w['seconds']:.1f} s)")


    for key in ("solve", "solve_clean"):
        if key in results:
            s = results[key]
            print(f"{key} ({s['frames']} frames, demo seed 0 -> demo seed 3 face): weight RMSE own rig vs truth "
                  f"{s['rmse_own_vs_truth']:.4f}, transferred vs truth {s['rmse_transferred_vs_truth']:.4f}, "
                  f"transferred vs own {s['rmse_transferred_vs_own']:.4f}")


if __name__ == "__main__":
    sys.exit(suite_main(run, __doc__))
