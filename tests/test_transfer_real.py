"""Rig transfer end to end between real rigs: the procedural demo rig and the ICT face (different topology)."""

import numpy as np
import pytest

from livecap.transfer import TransferOptions, transfer
from livecap.transfer.align import prealign
from livecap.transfer.labels import DEMO_TO_MULTIPIE, landmark_distances
from livecap.transfer.landmarks import detect_landmarks, eye_width
from livecap.transfer.surface import Surface

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def demo_on_ict(demo, ict):
    return transfer(*demo, ict[0].neutral, ict[0].triangles)


def test_demo_rig_onto_ict(demo, ict, demo_on_ict):
    (drig, dlay), (irig, ilay), res = demo, ict, demo_on_ict
    new = res.rig
    assert new.names == sorted(drig.names) and new.n_vertices == irig.n_vertices
    np.testing.assert_array_equal(new.triangles, irig.triangles)
    assert len(new.inbetweens) == len(drig.inbetweens) and len(new.correctives) == len(drig.correctives)
    assert res.layout.labels == dlay.labels and res.layout.stable.tolist() == dlay.stable.tolist()
    res.layout.check(new)
    for name in ("jawOpen", "eyeBlinkLeft", "mouthSmileLeft", "browInnerUp"):
        src = np.linalg.norm(drig.deltas[drig.index(name)], axis=1).max()
        dst = np.linalg.norm(new.deltas[new.index(name)], axis=1).max()
        assert 0.5 * src < dst < 2.0 * src, name
    # the neck, which the demo face does not have, stays still
    neck = irig.neutral[:, 1] < -120
    assert np.abs(new.deltas[:, neck]).max() < 1e-6
    # landmarks against ICT's own markers (labels matched through the demo/multi-PIE table)
    w, _ = eye_width(ilay, irig.neutral)
    ref = ilay.sampling_matrix(irig.n_vertices) @ irig.neutral
    rows = landmark_distances(dlay.labels, res.landmarks.points, ilay.labels, ref)
    assert len(rows) == len(DEMO_TO_MULTIPIE)
    print(f"\nlandmarks demo -> ICT, % of ICT's eye width ({w:.1f} mm):")
    for a, b, d in rows:
        print(f"  {a:10s} -> {b:9s} {d:6.2f} mm {d / w * 100:6.1f} %")
    # the demo's procedural anatomy is not ICT's (even the best similarity fitted to the true pairs leaves
    # a median 27 %): what holds is that every landmark lands in its own region of the face
    assert max(d for _, _, d in rows) < 1.0 * w
    assert res.landmarks.compatible.mean() > 0.9


def test_ict_rig_onto_demo(demo, ict):
    (drig, _), (irig, ilay) = demo, ict
    res = transfer(irig, ilay, drig.neutral, drig.triangles)
    new = res.rig
    assert new.names == sorted(irig.names) and new.n_vertices == drig.n_vertices
    assert res.layout.labels == ilay.labels
    assert "eye corners" in res.eye_width_source
    blink = np.linalg.norm(new.deltas[new.index("eyeBlink_L")], axis=1)
    top = new.neutral[np.argmax(blink)]
    assert top[0] > 10 and 0 < top[1] < 50  # the subject's left eye, not the mouth or the other eye
    jaw = np.linalg.norm(new.deltas[new.index("jawOpen")], axis=1)
    assert new.neutral[np.argmax(jaw), 1] < -40


def test_landmarks_on_a_warped_remeshed_ict(ict):
    """Ground truth known: ICT warped to other proportions, moved, decimated to half its triangles."""
    from benchmarks.transfer import warped_remeshed

    rig, layout = ict
    V, F, truth = warped_remeshed(rig, layout)
    src, dst = Surface(rig.neutral, rig.triangles), Surface(V, F)
    sim = prealign(src, dst)
    aligned = Surface(sim.apply(rig.neutral), rig.triangles)
    w = eye_width(layout, rig.neutral)[0] * sim.scale
    sites = layout.sampling_matrix(rig.n_vertices) @ aligned.vertices
    res = detect_landmarks(aligned, sites, layout.vertices[:, 0], dst, 0.5 * w)
    before = np.linalg.norm(sites - truth, axis=1) / w
    after = np.linalg.norm(res.points - truth, axis=1) / w
    print(f"\nwarped ICT: within 8 % of the eye width: {np.mean(before < 0.08):.0%} after pre-alignment, "
          f"{np.mean(after < 0.08):.0%} after detection (r_d = 0.5 eye widths); median {np.median(after):.1%}")
    assert np.mean(after < 0.08) > 0.5 and np.median(after) < np.median(before)


def test_solving_with_a_transferred_rig():
    """A take of face B solved with B's own rig and with the demo rig transferred onto B's neutral."""
    from benchmarks.transfer import solve_agreement

    r = solve_agreement(5.0)
    print(f"\nweight RMSE: own rig {r['rmse_own_vs_truth']:.4f}, transferred {r['rmse_transferred_vs_truth']:.4f}, "
          f"between {r['rmse_transferred_vs_own']:.4f}")
    assert r["rmse_transferred_vs_truth"] < r["rmse_own_vs_truth"] + 0.05
    assert r["rmse_transferred_vs_own"] < 0.2


def test_transfer_options_reach_the_pipeline(demo, ict):
    (drig, dlay) = demo
    res = transfer(drig, dlay, drig.neutral + [3.0, -2.0, 1.0], drig.triangles,
                   TransferOptions(prealign="rigid", eye_width=30.0, radius_fraction=(0.25, 0.06)))
    assert res.alignment.scale == 1.0 and res.eye_width == 30.0
    np.testing.assert_allclose(res.alignment.translation, [3.0, -2.0, 1.0], atol=1e-6)
