"""Issue 35: under model mismatch a weight is trusted only as far as its shape's own marker motion is seen."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from livecap.calibration.profile import Profile
from livecap.modes.quiet import EVIDENCE_FULL, EvidenceGate, mismatched
from livecap.modes.registry import build_solver
from livecap.offline.solve import solve_take
from solvers.observability import unique_evidence, whiten
from transport.takefile import read_take

REC = Path(__file__).resolve().parents[1] / "recordings"


def _partners_and_phantom(unique: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Columns a, b and c = a + b + e, e orthogonal to a and b with |e| = ``unique`` (mm): c is nearly its
    partners' blend (mouthFrown beside the jaw shapes)."""
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.normal(size=(30, 3)))
    a, b = 5.0 * Q[:, 0] + 1.0 * Q[:, 1], 4.0 * Q[:, 1]
    e = unique * Q[:, 2]
    return np.column_stack([a, b, a + b + e]), e


def test_the_unique_part_is_what_the_partners_cannot_make():
    B, e = _partners_and_phantom(0.3)
    E, d = unique_evidence(B, 0.5)
    assert d[2] == pytest.approx(0.3 / 0.5)  # 0.3 mm of its own motion per unit weight, in 0.5 mm noise sd
    assert E[2] @ e == pytest.approx(0.3 / 0.5)
    assert E[2] @ (B[:, 0] + B[:, 1]) == pytest.approx(0.0, abs=1e-9)  # the partners' motion is no evidence for it


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.floats(0.1, 3.0))
def test_own_evidence_per_unit_weight_is_the_unique_motion(seed, noise):
    """E[k] . b_k = d_k for every shape of any basis (the NNLS residual is orthogonal to the partners it uses)."""
    B = np.random.default_rng(seed).normal(size=(24, 6))
    E, d = unique_evidence(B, noise)
    np.testing.assert_allclose(np.einsum("kr,rk->k", E, B), d, rtol=1e-6, atol=1e-9)
    assert np.all(d >= 0) and np.all(d <= np.linalg.norm(B, axis=0) / noise + 1e-9)


def test_a_noisy_marker_counts_for_less():
    B = np.eye(6)[:, [0, 3]]  # shape 0 moves marker 0 (x), shape 1 marker 1 (x)
    Bw = whiten(B, 1.0, np.array([2.0, 0.5]))
    assert Bw[0, 0] < Bw[3, 1]  # the same 1 mm is fewer noise sd at the noisier marker
    np.testing.assert_allclose(whiten(B, 1.0, None), B)
    with pytest.raises(ValueError, match="marker_noise: 2 positive values"):
        whiten(B, 1.0, np.array([1.0, 1.0, 1.0]))


def test_the_gate_keeps_a_phantom_at_rest_when_only_its_partners_moved():
    B, e = _partners_and_phantom(3.0)
    gate = EvidenceGate(B, 0.5, None, np.ones(3, bool))
    valid = np.ones(10, bool)
    partners = (B[:, 0] + B[:, 1]).reshape(10, 3)  # the actor moved a and b only
    out = gate(np.array([0.5, 0.5, 0.5]), partners, valid)  # a solve that put half of it on the phantom
    assert out[2] == 0.0 and out[0] > 0.0 and out[1] > 0.0
    seen = (B[:, 2]).reshape(10, 3)  # the phantom's own motion (6 noise sd of unique evidence) is kept whole
    np.testing.assert_allclose(gate(np.array([0.0, 0.0, 1.0]), seen, valid), [0.0, 0.0, 1.0])
    assert EVIDENCE_FULL <= 3.0 / 0.5


@pytest.fixture(scope="module")
def take():
    return read_take(REC / "demo_take.c3d").slice(0, 240)


@pytest.mark.parametrize("mode", ["lsq", "robust", "kalman", "movement"])
def test_the_gate_runs_only_under_model_mismatch_and_only_lowers_weights(demo_profile_path, take, mode):
    p = Profile.load(demo_profile_path)
    tuned = p.settings["robust"]
    assert not mismatched(p)  # calibration on the demo neutral: jitter and residual agree
    assert getattr(build_solver(mode, p), "gate", None) is None
    q = replace(p, settings={**p.settings, "robust": {**tuned, "residual_mm": 10 * tuned["jitter_mm"]}})
    assert mismatched(q) and build_solver(mode, q).gate is not None
    loose = solve_take(take, p, build_solver(mode, p)).weights
    gated = solve_take(take, q, build_solver(mode, q)).weights
    assert np.all(np.abs(gated) <= np.abs(loose) + 1e-12)
    assert gated.sum() < loose.sum()


def test_streamed_evidence_is_the_takes_causal_average():
    """Frame by frame (``step``) the gate gives what it gives over the whole take (``solve``): one causal average."""
    B, _ = _partners_and_phantom(3.0)
    rng = np.random.default_rng(2)
    W = rng.uniform(0, 1, size=(40, 3))
    Y = (W @ B.T + rng.normal(scale=0.5, size=(40, 30))).reshape(40, 10, 3)
    valid = rng.uniform(size=(40, 10)) > 0.1
    gate = EvidenceGate(B, 0.5, None, np.ones(3, bool), rate=60.0)
    whole = gate(W, Y, valid)
    gate.reset()
    np.testing.assert_allclose(np.array([gate(W[i], Y[i], valid[i]) for i in range(40)]), whole, atol=1e-12)
    assert gate.keep > 0.5


def test_a_held_shape_is_no_partner():
    """eyeBlink beside a held eyeLookDown: a held shape explains nothing; the blink's evidence is all its motion."""
    rng = np.random.default_rng(3)
    a = rng.normal(size=30)
    B = np.column_stack([a, a + 0.05 * rng.normal(size=30)])  # nearly parallel: each is the other's partner
    both = EvidenceGate(B, 0.5, None, np.array([True, True]))
    alone = EvidenceGate(B, 0.5, None, np.array([False, True]))  # shape 0 held (at rest)
    y = B[:, 1].reshape(10, 3)
    W = np.array([0.0, 1.0])
    assert both(W, y, np.ones(10, bool))[1] < 1.0  # beside its partner, its own part is small
    assert alone(W, y, np.ones(10, bool))[1] == 1.0
    assert np.all(alone.E[0] == 0.0)


def test_streamed_the_gate_reads_the_frame_a_lagged_mode_publishes():
    """A mode with ``latency_frames`` L returns frame t - L's weights at step t: the gate must read frame t - L."""
    from livecap.modes.quiet import QuietShapes

    class Lagged:  # a stand-in for kalman / robust-lag: the weights of two frames ago
        latency_frames = 2

        def __init__(self):
            self.frames = []

        def step(self, target, valid):
            self.frames.append(float(target[0, 0]))
            return np.array([self.frames[max(0, len(self.frames) - 3)]])

        def reset(self):
            self.frames = []

    read = []

    class Spy:
        def __call__(self, W, targets, valid):
            read.append(float(targets[0, 0]))
            return W

        def reset(self):
            read.append("reset")

    q = QuietShapes(Lagged(), 1, np.array([0]), np.zeros(0, int), lambda kept: np.zeros((0,)), False, Spy())
    out = [q.step(np.full((2, 3), float(t)), np.ones(2, bool))[0] for t in range(6)]
    assert out == [0.0, 0.0, 0.0, 1.0, 2.0, 3.0] and read == [0.0, 0.0, 0.0, 1.0, 2.0, 3.0]
    q.reset()
    assert not q.seen and not q.inner.frames and read[-1] == "reset"


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000))
def test_the_gate_only_ever_pulls_toward_rest(seed):
    """Whatever the markers do, a gated weight keeps its sign and is never larger than the mode solved it."""
    rng = np.random.default_rng(seed)
    B = rng.normal(size=(18, 4)) * rng.uniform(0.1, 5.0, size=4)
    gate = EvidenceGate(B, 0.5, rng.uniform(0.2, 3.0, size=6), np.array([True, True, True, False]))
    W = rng.uniform(-1, 1, size=(20, 4))
    Y = rng.normal(scale=3.0, size=(20, 6, 3))
    out = gate(W, Y, rng.uniform(size=(20, 6)) > 0.2)
    assert np.all(np.abs(out) <= np.abs(W) + 1e-12) and np.all(out * W >= 0) and np.all(out[:, 3] == W[:, 3])


def test_the_gate_does_not_switch_within_a_frame():
    """Cheek take (issue 35): a weight crossing the 2-6 sd ramp in two frames jumped by its whole size. The factor
    now takes at least ``GATE_SWING_SECONDS`` from rest to whole, streamed and over a take alike."""
    from livecap.modes.quiet import GATE_SWING_SECONDS

    B, e = _partners_and_phantom(3.0)
    rate = 60.0
    W = np.tile([0.0, 0.0, 1.0], (40, 1))
    Y = np.zeros((40, 10, 3))
    Y[10:] = (20.0 * B[:, 2]).reshape(10, 3)  # from frame 10 on, far more than enough of its own motion at once
    W[10:, 2] = 20.0
    valid = np.ones((40, 10), bool)
    gate = EvidenceGate(B, 0.5, None, np.ones(3, bool), rate=rate)
    whole = gate(W, Y, valid)
    factor = whole[:, 2] / W[:, 2]
    assert factor[9] == 0.0 and factor[-1] == pytest.approx(1.0)
    assert np.max(np.diff(factor)) == pytest.approx(1.0 / (rate * GATE_SWING_SECONDS))
    gate.reset()
    np.testing.assert_allclose([gate(W[i], Y[i], valid[i]) for i in range(40)], whole, atol=1e-12)


def test_evidence_counts_in_the_noise_the_solve_leaves_now():
    """Calibrated on a neutral take, the noise misses what the rig cannot follow while the actor acts (the
    model-mismatch takes: 0.125 mm at neutral). The evidence is then read in the residual's own sd when that is
    larger, so motion the solve leaves unexplained everywhere does not make a partner's blend look like evidence."""
    B, e = _partners_and_phantom(3.0)
    rng = np.random.default_rng(4)
    free = np.linalg.qr(np.column_stack([B, rng.normal(size=(30, 10))]))[0][:, 3:]  # directions no shape makes
    W = np.array([0.0, 0.0, 1.0])
    fits = B[:, 2].reshape(10, 3)
    misfit = (B[:, 2] + free @ rng.normal(scale=3.0, size=10)).reshape(10, 3)  # ~6 sd of misfit per coordinate
    valid = np.ones(10, bool)
    gate = EvidenceGate(B, 0.5, None, np.ones(3, bool))
    assert gate(W, fits, valid)[2] == pytest.approx(1.0)
    assert gate(W, misfit, valid)[2] < 0.5
    quiet = EvidenceGate(B, 0.5, None, np.ones(3, bool))  # residual at the calibrated noise: unchanged
    small = (B[:, 2] + free @ rng.normal(scale=0.1, size=10)).reshape(10, 3)
    assert quiet(W, small, valid)[2] == pytest.approx(1.0)
