"""Labelling a face among many points (issue 36 item 11): another checkout's labeller against this
tree's, interleaved frame by frame (thread CPU time), on the demo take's first FRAMES frames among
GHOSTS points uniform in a 2 m cube about the face (seed 0), calibrated on recordings/demo_neutral.c3d.

    python -m benchmarks.labelling_crowd /work/main [FRAMES] [GHOSTS]
"""

import importlib.util
import os
import sys
import time
from pathlib import Path

import numpy as np

from livecap.calibration.profile import calibrate, estimate_neutral
from livecap.core.markers import MarkerLayout
from livecap.core.rig import Rig
from livecap.demo.unlabelled import in_a_crowd
from livecap.live.unlabelled import labeller_for
from transport.takefile import read_take

REC = Path(__file__).resolve().parents[1] / "recordings"
spec = importlib.util.spec_from_file_location("other_labelling", Path(sys.argv[1]) / "solvers" / "labelling.py")
ml = importlib.util.module_from_spec(spec)
sys.modules["other_labelling"] = ml
spec.loader.exec_module(ml)
rig = Rig.load(REC / "demo_rig.npz")
layout = MarkerLayout.load(REC / "demo_rig.markers.json", rig)
prof = calibrate(rig, layout, estimate_neutral(read_take(REC / "demo_neutral.c3d").select(layout.labels),
                                               layout.stable, 120))
take = read_take(REC / "demo_take.c3d").select(prof.labels)
N = int(sys.argv[2]) if len(sys.argv) > 2 else 600
K = int(sys.argv[3]) if len(sys.argv) > 3 else 2340
clouds = in_a_crowd(take, N, K)
old = ml.MarkerLabeller(prof.source_neutral, prof.stable, prof.basis, prof.lower, prof.upper)
new = labeller_for(prof)
to, tn, same = [], [], 0
load0 = os.getloadavg()[0]
for c in clouds:
    t0 = time.thread_time()
    a = old.step(c)
    to.append(time.thread_time() - t0)
    t0 = time.thread_time()
    near = new.near(c)
    b = new.step(c if near is None else c[near])
    tn.append(time.thread_time() - t0)
    same += np.array_equal(a.valid, b.valid) and np.array_equal(a.positions[a.valid], b.positions[b.valid])
to, tn = np.array(to) * 1e3, np.array(tn) * 1e3
print(f"{N} frames, face + {K} ghosts; load {load0:.1f}->{os.getloadavg()[0]:.1f}; same labels on {same}/{N} frames")
for name, t in ((sys.argv[1], to), ("this", tn)):
    print(f"{name}: first frame {t[0]:.0f} ms; step median {np.median(t[1:]):.2f} "
          f"p99 {np.percentile(t[1:], 99):.2f} max {t[1:].max():.1f} ms (thread CPU)")
