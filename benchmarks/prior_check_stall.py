"""The streamed prior check's cost to a live session: ``kalman``'s step paced at the take's rate (issue 41.2).

An ICT take driven by S07-001 (6 s, 0.5 mm), the prior from the other performers (benchmarks.prior_lopo), each frame
given to ``step`` on its tick as a live source would: once with the check run inside the step that completes the
first SUPPORT_SECONDS (and each later window), once in its thread and used SUPPORT_SWAP x its window (at most
SUPPORT_SWAP_MAX s) later (the default). Prints step times.

    python -m benchmarks.prior_check_stall
"""

from __future__ import annotations

import time

import numpy as np


def main() -> int:
    from benchmarks.prior_lopo import PERFORMERS
    from livecap.calibration.animation_prior import build_prior
    from livecap.calibration.targets import prepare_targets
    from livecap.cli.realeval import _realdata, _rig
    from livecap.demo.curves_take import CurveTakeSettings, curves_take
    from livecap.modes import marker_kalman
    from livecap.modes.registry import build_solver
    from livecap.offline.real_eval import plain_profile

    rig, layout = _rig("ict")
    folder = _realdata() / "performance"
    name = "S07-001"
    others = [folder / f"{o}.csv" for o, who in PERFORMERS.items() if who != PERFORMERS[name]]
    ct = curves_take(rig, layout, folder / f"{name}.csv", CurveTakeSettings(start=10, seconds=6, noise_mm=0.5))
    profile = plain_profile(rig, layout, ct)
    profile.prior = build_prior(others, rig.names, rig.lower, rig.upper)
    take, targets, _, _ = prepare_targets(ct.take, profile)
    swap = marker_kalman.SUPPORT_SWAP
    most = marker_kalman.SUPPORT_SWAP_MAX
    later = f"in a thread, used {swap:g} x its window, <= {most:g} s, later"
    for label, share in (("in the step", 0.0), (later, swap)):
        marker_kalman.SUPPORT_SWAP = share
        solver = build_solver("kalman", profile, {"rate": ct.take.rate})
        dt, t0, ms = 1.0 / ct.take.rate, time.perf_counter(), []
        for i in range(len(targets)):
            while time.perf_counter() < t0 + i * dt:
                time.sleep(0.0005)
            a = time.perf_counter()
            solver.step(targets[i], take.valid[i])
            ms.append((time.perf_counter() - a) * 1e3)
        ms = np.array(ms)
        print(f"paced at {ct.take.rate:g} Hz, check {label}: step p50 {np.median(ms):.2f} ms, p99 "
              f"{np.percentile(ms, 99):.2f}, max {ms.max():.1f} ms, frames over 1/rate {int((ms > dt * 1e3).sum())}")
    marker_kalman.SUPPORT_SWAP = swap
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
