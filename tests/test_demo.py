import re

import numpy as np

from livecap.demo.face import demo_rig
from livecap.demo.performance import PerformanceSettings, perform

ARKIT = re.compile(r"^(eye|jaw|mouth|brow|cheek|nose)[A-Z][A-Za-z]*$")


def test_demo_rig_meets_its_spec(demo):
    rig, layout = demo
    assert rig.n_vertices >= 3000 and rig.n_shapes >= 40
    assert all(ARKIT.match(n) for n in rig.names)
    for name in ("eyeBlinkLeft", "jawOpen", "mouthSmileLeft", "browInnerUp"):
        assert name in rig.names
    assert rig.inbetweens and rig.correctives
    assert 55 <= layout.n_markers <= 70 and layout.stable.sum() >= 4
    # every shape is seen by the markers, and the basis has full column rank
    B = layout.basis(rig)
    assert np.linalg.matrix_rank(B) == rig.n_shapes
    # shapes are local: each moves well under half of the vertices noticeably
    moved = (np.linalg.norm(rig.deltas, axis=2) > 0.1).mean(axis=1)
    assert moved.max() < 0.5


def test_demo_rig_is_deterministic():
    a, la = demo_rig(5)
    b, lb = demo_rig(5)
    np.testing.assert_array_equal(a.deltas, b.deltas)
    assert la.labels == lb.labels
    c, _ = demo_rig(6)
    assert not np.allclose(a.deltas, c.deltas)


def test_performance_has_what_a_take_needs(demo):
    rig, layout = demo
    s = PerformanceSettings(seconds=10, noise_mm=0.5, occlusion=0.03)
    p = perform(rig, layout, s)
    assert p.take.n_frames == 1200 and p.weights.shape == (1200, rig.n_shapes)
    assert np.all(p.weights[: int(s.neutral_start * s.rate)] == 0)  # neutral start
    assert p.weights.max() > 1.0  # some poses beyond the rig's limits
    blink = p.weights[:, rig.index("eyeBlinkLeft")]
    assert (np.diff((blink > 0.5).astype(int)) == 1).sum() >= 2  # several blinks
    missing = 1 - p.take.valid.mean()
    assert 0.02 < missing < 0.06
    ang = np.degrees(np.linalg.norm(
        __import__("scipy.spatial.transform", fromlist=["Rotation"]).Rotation.from_quat(p.head_rotation).as_rotvec(),
        axis=1))
    assert 5 < ang.max() <= 25
    # actor proportions differ from the rig's
    sites = layout.marker_rig(rig).neutral
    assert np.abs(np.ptp(p.actor_neutral, 0) / np.ptp(sites, 0) - 1).max() > 0.02
