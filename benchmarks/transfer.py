"""Rig transfer (Xiang et al. 2008): timing on ~10,000-vertex faces, landmark accuracy, solve agreement.

    python -m benchmarks.transfer [--quick] [--json OUT.json]

* demo -> ICT (9,409 vertices) and ICT -> demo at 10,152 vertices: seconds per stage;
* landmark detection demo -> ICT against ICT's own markers (labels matched through
  livecap.transfer.labels), per landmark, in % of ICT's eye width (Xiang Fig. 5's unit);
  the floor: the same labels after a similarity fitted to the true pairs;
* landmark detection ICT -> ICT warped (livecap.demo.performance.actor_warp), moved and
  decimated to half its triangles (ground truth known), with the default pipeline (smooth warp,
  then Algorithm 1 at r_d = 6 %) and without the warp (Xiang's similarity pre-alignment only);
* solving: demo rig (seed 0) transferred onto another demo face (seed 3, other resolution);
  a take performed by that face's own rig is solved with its own rig and with the transferred
  one: weight RMSE of each against the truth and between the two, and each rig's noise
  amplification at its markers (the weight standard deviation 0.5 mm of marker noise causes in
  an unbounded least-squares fit: bounded lsq turns it into a bias, see docs/transfer.md), once
  more with a ridge (``RIDGE``) that removes that bias.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.timing import suite_main
from livecap.transfer import TransferOptions, transfer
from livecap.transfer.align import _umeyama
from livecap.transfer.labels import landmark_distances
from livecap.transfer.landmarks import eye_width

RIDGE = 10.0  # mm^2 per unit weight^2: enough to stop bounded lsq turning marker noise into weight bias
SHARED = Path(os.environ.get("LIVECAP_SHARED") or Path(__file__).resolve().parents[1].parent / "shared")
ICT = SHARED / "realdata" / "ict-face"


def _ict():
    from livecap.core.markers import MarkerLayout
    from livecap.core.rig import Rig

    rig = Rig.load(ICT)
    return rig, MarkerLayout.load(ICT / "markers.json", rig)


def landmark_report(result, generic_rig, generic_layout, reference_rig, reference_layout) -> dict:
    """Per-landmark distances (mm and % of the reference's eye width) of detected vs reference markers."""
    w_ref, _ = eye_width(reference_layout, reference_rig.neutral)
    ref_pts = reference_layout.sampling_matrix(reference_rig.n_vertices) @ reference_rig.neutral
    rows = landmark_distances(generic_layout.labels, result.landmarks.points, reference_layout.labels, ref_pts)
    pct = np.array([d / w_ref * 100 for _, _, d in rows])
    # floor: the generic's own sites after the similarity fitted to the true pairs (no surface involved)
    sites = generic_layout.sampling_matrix(generic_rig.n_vertices) @ generic_rig.neutral
    idx = [generic_layout.labels.index(a) for a, _, _ in rows]
    ref = np.array([ref_pts[reference_layout.labels.index(b)] for _, b, _ in rows])
    floor = np.linalg.norm(_umeyama(sites[idx], ref, True).apply(sites[idx]) - ref, axis=1) / w_ref * 100
    table = [(a, b, d, d / w_ref * 100, f) for (a, b, d), f in zip(rows, floor, strict=True)]
    return {"eye_width_mm": w_ref, "rows": table,
            "within_8pct": int((pct < 8).sum()), "n": len(rows), "median_pct": float(np.median(pct)),
            "floor_within_8pct": int((floor < 8).sum()), "floor_median_pct": float(np.median(floor))}


def warped_remeshed(rig, layout, seed: int = 7):
    """A face with a known answer: ``rig`` warped to other proportions, moved, decimated to half
    its triangles; returns its vertices, triangles and where ``layout``'s markers truly are."""
    import igl
    from scipy.spatial.transform import Rotation

    from livecap.demo.performance import actor_warp

    warp = actor_warp(np.random.default_rng(seed))
    R = Rotation.from_rotvec([0.1, 0.15, 0.05]).as_matrix()

    def move(p):
        return warp(p) @ R.T + np.array([5.0, -20.0, 12.0])

    V, F, _, _ = igl.decimate(move(rig.neutral), rig.triangles, len(rig.triangles) // 2)
    return V, F, move(layout.sampling_matrix(rig.n_vertices) @ rig.neutral)


def warped_ict_accuracy(warp: bool = True, seed: int = 7) -> dict:
    """Share of ICT's landmarks detected within 8 % of the eye width on a warped, moved, decimated ICT."""
    from livecap.transfer.align import prealign
    from livecap.transfer.landmarks import detect_landmarks
    from livecap.transfer.surface import Surface
    from livecap.transfer.warp import smooth_warp

    rig, layout = _ict()
    V, F, truth = warped_remeshed(rig, layout, seed)
    opt = TransferOptions() if warp else TransferOptions(warp=())
    t0 = time.perf_counter()
    target = Surface(V, F)
    sim = prealign(Surface(rig.neutral, rig.triangles), target, opt.prealign)
    w = eye_width(layout, rig.neutral)[0] * sim.scale
    x = sim.apply(rig.neutral)
    if opt.warp:
        x = smooth_warp(x, rig.triangles, target, w, opt.warp).vertices
    S = layout.sampling_matrix(rig.n_vertices)
    centres = layout.vertices[np.arange(layout.n_markers), np.argmax(layout.barycentric, axis=1)]
    lm = detect_landmarks(Surface(x, rig.triangles), S @ x, centres, target, opt.radius_fraction * w)
    seconds = time.perf_counter() - t0
    err = np.linalg.norm(lm.points - truth, axis=1) / w * 100
    before = np.linalg.norm(S @ x - truth, axis=1) / w * 100
    return {"warp": warp, "seed": seed, "within_8pct": float((err < 8).mean()), "median_pct": float(np.median(err)),
            "before_detection_within_8pct": float((before < 8).mean()), "seconds": seconds}


def solve_agreement(seconds: float = 20.0, clean: bool = False, ridge: float = 0.0) -> dict:
    """Weight RMSE: a take of face B solved with B's own rig vs with the demo rig transferred onto B."""
    from livecap.calibration.profile import calibrate, estimate_neutral
    from livecap.demo.face import demo_rig
    from livecap.demo.performance import PerformanceSettings, perform
    from livecap.modes.registry import build_solver
    from livecap.offline.metrics import weight_rmse
    from livecap.offline.solve import solve_take

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
    weights, amp = {}, {}
    for name, rig, layout in (("own", own, own_layout), ("transferred", res.rig, res.layout)):
        take = perf.take.select(layout.labels)
        profile = calibrate(rig, layout, estimate_neutral(take, layout.stable, int(take.rate)))
        solved = solve_take(take, profile, build_solver("lsq", profile, {"ridge": ridge}))
        weights[name] = solved.weights[:, [rig.names.index(n) for n in perf.names]]
        # 0.5 mm of marker noise -> weight standard deviation of an unbounded fit, median over shapes
        amp[name] = float(np.median(0.5 * np.sqrt(np.diag(np.linalg.inv(profile.basis.T @ profile.basis)))))
    return {"transfer_seconds": elapsed, "frames": len(perf.weights), "noise_amplification": amp, "ridge": ridge,
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
                            "landmarks": landmark_report(res, demo, demo_layout, ict, ict_layout)}
    if not quick:
        big, big_layout = demo_rig(0, resolution=(108, 94))
        res2 = transfer(ict, ict_layout, big.neutral, big.triangles)
        results["ict->demo10k"] = {"target_vertices": big.n_vertices, "seconds": res2.seconds,
                                   "total_seconds": float(sum(res2.seconds.values()))}
        results["warped-ict"] = [warped_ict_accuracy(True, seed) for seed in (7, 1, 2, 3)]
        results["warped-ict"].append(warped_ict_accuracy(False))
    results["solve"] = solve_agreement(5.0 if quick else 20.0)
    results["solve_ridge"] = solve_agreement(5.0 if quick else 20.0, ridge=RIDGE)
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
              f"{lm['within_8pct']}/{lm['n']} within 8 %, median {lm['median_pct']:.1f} %; floor (similarity on the "
              f"true pairs) {lm['floor_within_8pct']}/{lm['n']}, median {lm['floor_median_pct']:.1f} %")
        print("  label      -> ICT        detected mm, % eye width | floor %")
        for a, b, d, p, f in lm["rows"]:
            print(f"  {a:10s} -> {b:9s} {d:6.2f} mm  {p:6.1f} % | {f:6.1f} %")
    for w in results.get("warped-ict", []):
        print(f"landmarks ICT -> warped ICT (seed {w['seed']}), {'smooth warp + ' if w['warp'] else 'similarity + '}"
              f"Algorithm 1 at r_d = 6 %: {w['within_8pct'] * 100:.0f} % within 8 % (before detection "
              f"{w['before_detection_within_8pct'] * 100:.0f} %), median {w['median_pct']:.1f} % "
              f"({w['seconds']:.1f} s)")

    for key in ("solve", "solve_ridge", "solve_clean"):
        if key in results:
            s = results[key]
            print(f"{key} (lsq ridge {s['ridge']:g} mm^2, {s['frames']} frames, demo seed 0 -> demo seed 3 face): "
                  f"weight RMSE own rig vs truth "
                  f"{s['rmse_own_vs_truth']:.4f}, transferred vs truth {s['rmse_transferred_vs_truth']:.4f}, "
                  f"transferred vs own {s['rmse_transferred_vs_own']:.4f}; noise amplification (weight sd per 0.5 mm, "
                  f"median) own {s['noise_amplification']['own']:.3f}, transferred "
                  f"{s['noise_amplification']['transferred']:.3f}")


if __name__ == "__main__":
    sys.exit(suite_main(run, __doc__))
