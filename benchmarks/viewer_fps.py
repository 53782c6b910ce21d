"""Offscreen preview frames per second: GPU deformation vs a CPU-deformed upload, same run.

Demo rig (3584 vertices, 43 shapes + 3 in-betweens + 4 correctives), 640x480, EGL standalone
context (on a machine without a GPU: Mesa llvmpipe). Weights are the demo take's ground-truth
curves, so the active-field count is realistic. "frame" = deform + lit draw + marker overlay +
read-back to a numpy image; "annotated" adds the weight bars and caption (OpenCV).

    python -m benchmarks.viewer_fps [--quick] [--json benchmarks/results/viewer_fps.json]
"""

from __future__ import annotations

import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.timing import suite_main

ROOT = Path(__file__).resolve().parents[1]


def _weights(rig, n: int) -> np.ndarray:
    from livecap.demo.performance import GroundTruth

    truth = ROOT / "recordings" / "demo_take.truth.npz"
    if truth.exists():
        gt = GroundTruth.load(truth)
        W = gt.weights[:, [gt.names.index(name) for name in rig.names]]
        return W[np.linspace(len(W) * 0.1, len(W) * 0.9, n).astype(int)]
    rng = np.random.default_rng(0)
    return rng.uniform(0, 0.6, (n, rig.n_shapes)) * (rng.random((n, rig.n_shapes)) < 0.3)


def _fps(fn, W) -> tuple[float, float]:
    """Frames per wall-clock second, and CPU milliseconds per frame (this process, all its threads)."""
    fn(W[0])  # warm-up: shader compile, first upload
    start, cpu = time.perf_counter(), time.process_time()
    for w in W:
        fn(w)
    return len(W) / (time.perf_counter() - start), (time.process_time() - cpu) / len(W) * 1e3


def run(quick: bool = False) -> dict:
    from livecap.demo.face import demo_rig
    from viewer.compose import Caption
    from viewer.preview import Preview

    rig, layout = demo_rig(0)
    n = 30 if quick else 120
    W = _weights(rig, n)
    results: dict = {"rig": "demo (seed 0)", "vertices": rig.n_vertices, "triangles": int(len(rig.triangles)),
                     "shapes": rig.n_shapes, "size": "640x480", "frames": n,
                     "machine": f"{platform.machine()} {platform.processor() or ''}".strip(), "cpus": os.cpu_count(),
                     "load_before": os.getloadavg()[0], "lp_num_threads": os.environ.get("LP_NUM_THREADS", "default"),
                     "rows": []}
    for deformation in ("gpu", "cpu"):
        for samples in (0, 4):
            pv = Preview(rig, layout, size=(640, 480), samples=samples, deformation=deformation)
            r = pv.renderer
            results["renderer"] = r.ctx.info["GL_RENDERER"]
            markers = r.sites(np.zeros(rig.n_shapes)) + 1.0

            def deform_only(w, r=r):
                r.deform(w)
                r.ctx.finish()

            row = {"deformation": deformation, "msaa": samples}
            for key, fn in (("deform", deform_only), ("frame", lambda w, r=r, m=markers: r.render(w, None, m)),
                            ("annotated", lambda w, pv=pv: pv.draw(w, caption=Caption(0, 0.0, 0.1, "bench")))):
                row[f"{key}_fps"], row[f"{key}_cpu_ms"] = _fps(fn, W)
            results["rows"].append(row)
            r.release()
    print_table(results)
    return results


def print_table(res: dict) -> None:
    print(f"viewer offscreen fps: {res['rig']}, {res['vertices']} vertices, {res['shapes']} shapes, {res['size']}, "
          f"{res['frames']} frames, {res['renderer']}")
    print(f"load average before the run: {res['load_before']:.2f} on {res['cpus']} CPUs; "
          f"LP_NUM_THREADS={res['lp_num_threads']}")
    print(f"{'deformation':11s} {'msaa':>4s} {'deform/s':>9s} {'frames/s':>9s} {'annotated/s':>11s}   "
          f"{'cpu ms: deform':>14s} {'frame':>6s} {'annotated':>9s}")
    for row in res["rows"]:
        print(f"{row['deformation']:11s} {row['msaa']:4d} {row['deform_fps']:9.1f} {row['frame_fps']:9.1f} "
              f"{row['annotated_fps']:11.1f}   {row['deform_cpu_ms']:14.2f} {row['frame_cpu_ms']:6.2f} "
              f"{row['annotated_cpu_ms']:9.2f}")


if __name__ == "__main__":
    sys.exit(suite_main(run, __doc__))
