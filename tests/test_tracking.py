"""Constant-velocity Kalman and IMM weight filters (solvers/tracking.py): their defining properties."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from solvers.tracking import (
    IMMFilter,
    KalmanCV,
    NoiseShrink,
    RotatedIMM,
    alpha_beta_gains,
    dwna_variance,
    shared_markers,
)
from tests.imm_reference import NumpyIMMFilter


def batch_posterior_last(y: np.ndarray, q: float, r: float, v_var: float) -> float:
    """Posterior mean of x_{T-1} from the whole stacked linear-Gaussian problem (independent of the filter):
    unknowns x0, v0, u_1..u_{T-1} (DWNA: s_t = F s_{t-1} + G u_t, u ~ N(0, q)); flat prior on x0,
    N(0, v_var) on v0, y_t = x_t + N(0, r)."""
    T = len(y)
    n = 2 + (T - 1)
    F, G = np.array([[1.0, 1.0], [0.0, 1.0]]), np.array([0.5, 1.0])
    # s_t as a linear map of the unknowns
    maps = [np.zeros((2, n))]
    maps[0][0, 0] = maps[0][1, 1] = 1.0
    for t in range(1, T):
        M = F @ maps[-1]
        M[:, 1 + t] += G
        maps.append(M)
    A = np.array([M[0] for M in maps]) / np.sqrt(r)
    prior = np.diag(np.r_[0.0, 1.0 / v_var, np.full(T - 1, 1.0 / q)])
    z = np.linalg.solve(A.T @ A + prior, A.T @ (y / np.sqrt(r)))
    return float(maps[-1][0] @ z)


def test_kalman_equals_the_batch_posterior():
    rng = np.random.default_rng(3)
    y = np.cumsum(rng.normal(size=7)) * 0.3
    q, r, v_var = 0.02, 0.5, 0.7
    out = KalmanCV(q, r, v_var).filter(y[:, None])[:, 0]
    for T in (2, 4, 7):
        assert abs(out[T - 1] - batch_posterior_last(y[:T], q, r, v_var)) < 1e-10


def test_steady_state_gains_are_the_alpha_beta_filter():
    q, r = np.array([1e-6, 1e-4, 1e-2]), np.array([0.01, 0.01, 0.04])
    kf = KalmanCV(q, r)
    kf.filter(np.zeros((3000, 3)))
    alpha, beta = alpha_beta_gains(q, r)
    np.testing.assert_allclose(kf.gain[0], alpha, rtol=1e-6)
    np.testing.assert_allclose(kf.gain[1], beta, rtol=1e-6)


def test_no_steady_state_lag_on_a_ramp():
    t = np.arange(600.0)
    ramp = 0.2 + 0.004 * t
    out = KalmanCV(1e-7, 0.01).filter(ramp[:, None])[:, 0]
    assert abs(out[-1] - ramp[-1]) < 1e-6  # a first-order smoother would trail by slope x lag
    imm = IMMFilter(1e-8, 1e-4, 0.01).filter(ramp[:, None])[:, 0]
    assert abs(imm[-1] - ramp[-1]) < 1e-6


def test_imm_of_two_equal_models_is_the_kalman_filter():
    rng = np.random.default_rng(5)
    Y = rng.normal(size=(50, 4)).cumsum(0)
    r = np.array([0.1, 0.2, 0.3, 0.4])
    np.testing.assert_allclose(IMMFilter(1e-3, 1e-3, r).filter(Y), KalmanCV(1e-3, r, r).filter(Y), atol=1e-12)


def test_imm_smooths_a_still_channel_and_follows_an_onset():
    """Holds like the low-noise model while still, follows like the high-noise one after an onset."""
    rng = np.random.default_rng(7)
    T, onset = 600, 400
    truth = np.where(np.arange(T) < onset, 0.0, 0.02 * (np.arange(T) - onset))
    y = (truth + rng.normal(0, 0.05, T))[:, None]
    r, q_hold, q_move = 0.05**2, dwna_variance(0.5, 120), dwna_variance(80, 120)
    imm = IMMFilter(q_hold, q_move, r).filter(y)[:, 0]
    move = KalmanCV(q_move, r).filter(y)[:, 0]
    hold = KalmanCV(q_hold, r).filter(y)[:, 0]
    still = slice(100, onset)
    after = slice(onset + 30, onset + 80)
    def jitter(x):
        return np.mean(np.abs(np.diff(x, 2)))

    assert jitter(imm[still]) < 0.5 * jitter(move[still])
    assert np.mean(np.abs(imm[after] - truth[after])) < 0.1 * np.mean(np.abs(hold[after] - truth[after]))


def test_missing_samples_are_predicted_through():
    y = np.linspace(0, 1, 40)[:, None] * np.ones((1, 2))
    valid = np.ones((40, 2), bool)
    valid[10:20, 0] = False
    for f in (KalmanCV(1e-6, 0.01), IMMFilter(1e-8, 1e-4, 0.01)):
        out = f.filter(np.where(valid, y, np.nan), valid)
        assert np.all(np.isfinite(out))
        assert np.max(np.abs(out - y)) < 0.05  # the gap is bridged along the line


@given(st.floats(-5, 5), st.integers(0, 2**16))
def test_offset_equivariance(offset, seed):
    """Adding a constant to the input adds it to the output (the CV model has no preferred level)."""
    Y = np.random.default_rng(seed).normal(size=(30, 3)).cumsum(0) * 0.1
    for make in (lambda: KalmanCV(1e-3, 0.05), lambda: IMMFilter(1e-6, 1e-2, 0.05)):
        np.testing.assert_allclose(make().filter(Y + offset), make().filter(Y) + offset, atol=1e-9)


def _imm_pair(seed: int, shape: tuple, per_channel: bool, sojourn: float) -> tuple:
    rng = np.random.default_rng(seed)
    r = rng.uniform(1e-4, 1e-1, shape) if per_channel else float(rng.uniform(1e-4, 1e-1))
    q_hold, q_move = 10 ** rng.uniform(-10, -6), 10 ** rng.uniform(-5, -2)
    return IMMFilter(q_hold, q_move, r, sojourn), NumpyIMMFilter(q_hold, q_move, r, sojourn)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**16), st.sampled_from([(1,), (7,), (53,), (4, 3)]), st.booleans(),
       st.floats(1.5, 500), st.sampled_from([0.0, 0.05, 0.5]))
def test_compiled_imm_equals_the_numpy_reference(seed, shape, per_channel, sojourn, missing):
    """The compiled IMM (solvers/imm_kernels.py) gives the whole-array numpy version's weights, stepped and
    over a whole take, with missing samples (NaN where not valid) and onsets (steps) in the input."""
    rng = np.random.default_rng(seed + 1)
    T = 60
    Y = np.cumsum(rng.normal(0, 0.05, (T, *shape)), 0) + rng.normal(0, 0.02, (T, *shape))
    Y[T // 2:] += rng.normal(0, 1, shape) * (rng.random(shape) < 0.3)  # onsets
    valid = rng.random((T, *shape)) >= missing
    Y[~valid] = np.nan
    new, ref = _imm_pair(seed, shape, per_channel, sojourn)
    expected = ref.filter(Y, valid)
    np.testing.assert_allclose(new.filter(Y, valid), expected, rtol=0, atol=1e-12)
    new.reset()
    stepped = np.stack([new.step(Y[t], valid[t]) for t in range(T)])
    np.testing.assert_allclose(stepped, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(new.move_probability, ref.move_probability, rtol=0, atol=1e-12)
    if missing == 0.0:  # valid omitted: the same numbers
        np.testing.assert_allclose(new.filter(Y), expected, rtol=0, atol=1e-12)
        np.testing.assert_allclose(new.filter(Y[::-1]), ref.filter(Y[::-1]), rtol=0, atol=1e-12)


def test_imm_refuses_a_sample_of_another_channel_count():
    """The compiled step indexes its state by channel: a longer sample must be an error, not a read past it."""
    f = IMMFilter(1e-4, 1e-2, 0.01)
    f.step(np.zeros(3))
    with pytest.raises(ValueError, match="tracks 3 channels, got a sample of 6"):
        f.step(np.zeros(6))


def test_rotated_imm_along_the_channels_is_the_imm():
    rng = np.random.default_rng(9)
    Y = rng.normal(size=(40, 3)).cumsum(0)
    r = np.array([0.1, 0.2, 0.3])
    rotated = RotatedIMM(np.eye(3)[:, [2, 0, 1]], IMMFilter(1e-4, 1e-2, 1.0))
    rotated.set_noise(rotated.along(np.diag(r)))
    np.testing.assert_allclose(np.array([rotated.step(y) for y in Y]), IMMFilter(1e-4, 1e-2, r).filter(Y),
                               atol=1e-12)


def test_rotated_imm_without_axes_is_the_per_shape_imm_on_the_diagonal():
    """No axes (the 1000-shape rigs, where the rotation's two m x m products cost ~1 ms a frame): the plain IMM,
    its noise the covariance's diagonal."""
    rng = np.random.default_rng(11)
    Y = rng.normal(size=(40, 3)).cumsum(0)
    cov = np.array([[0.1, 0.05, 0.0], [0.05, 0.2, 0.01], [0.0, 0.01, 0.3]])
    plain = RotatedIMM(None, IMMFilter(1e-4, 1e-2, 1.0))
    plain.set_noise(plain.along(cov))
    np.testing.assert_allclose(np.array([plain.step(y) for y in Y]),
                               IMMFilter(1e-4, 1e-2, np.diag(cov)).filter(Y), atol=1e-12)


def test_rotated_imm_holds_the_noisy_difference_and_follows_the_sum():
    """Two weights whose fit noise is anticorrelated (as eyeWide / eyeLookUp): their sum is well seen, their
    difference badly. Run along the noise's eigenvectors the step in the sum is followed at once, as steady as a
    per-weight IMM given the same per-weight variances, which lags it (a blink's onset, the vertex p95)."""
    rng = np.random.default_rng(10)
    T, onset, rate = 600, 300, 60.0
    cov = 0.01 * np.array([[1.0, -0.98], [-0.98, 1.0]])
    truth = np.where(np.arange(T)[:, None] < onset, 0.2, 0.5) * np.ones((1, 2))
    Y = truth + rng.multivariate_normal(np.zeros(2), cov, T)
    q_hold, q_move = dwna_variance(0.5, rate), dwna_variance(80.0, rate)
    rotated = RotatedIMM(np.linalg.eigh(cov)[1], IMMFilter(q_hold, q_move, 1.0))
    rotated.set_noise(rotated.along(cov))
    out = np.array([rotated.step(y) for y in Y])
    plain = IMMFilter(q_hold, q_move, np.diag(cov)).filter(Y)
    def jitter(W):
        return np.mean(np.abs(np.diff(W[100:onset], 2, axis=0)))

    after = slice(onset, onset + 30)
    err, err_plain = np.abs(out[after] - truth[after]).mean(), np.abs(plain[after] - truth[after]).mean()
    assert jitter(out) <= 1.1 * jitter(plain)
    assert err < 0.6 * err_plain  # 0.43 x


def _shrink_pair(warm: int = 60) -> tuple[RotatedIMM, RotatedIMM]:
    q_hold, q_move = dwna_variance(0.5, 60.0), dwna_variance(80.0, 60.0)
    r = np.array([0.05, 1e-4])  # the fit's nominal variances: direction 0 ill-seen, 1 well seen
    plain = RotatedIMM(np.eye(2), IMMFilter(q_hold, q_move, r))
    shrunk = RotatedIMM(np.eye(2), IMMFilter(q_hold, q_move, r), NoiseShrink(warm_frames=warm))
    return plain, shrunk


def _wander_and_signal(T: int = 900, seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Direction 0: at rest (0.3) under a slow wander plus white noise of the same size, as the fit's error along
    an ill-seen direction; direction 1: a real slow motion under a little white noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(T)
    truth = np.stack([np.full(T, 0.3), 0.5 + 0.4 * np.sin(2 * np.pi * t / 240)], 1)
    wander = np.zeros(T)
    for i in range(1, T):
        wander[i] = 0.98 * wander[i - 1] + rng.normal(0, 0.03 * np.sqrt(1 - 0.98**2))
    Y = truth.copy()
    Y[:, 0] += wander + rng.normal(0, 0.03, T)
    Y[:, 1] += rng.normal(0, 0.01, T)
    return Y, truth


def test_noise_shrink_pulls_a_wandering_noise_direction_to_its_mean_and_keeps_the_signal():
    """Issue 41: the IMM's hold model keeps a slow wander as signal; where a direction's spread is mostly its own
    frame noise the shrink pulls it to its mean. On a direction with real motion it changes next to nothing."""
    Y, truth = _wander_and_signal()
    plain, shrunk = _shrink_pair()
    P = np.array([plain.step(y) for y in Y])
    S = np.array([shrunk.step(y) for y in Y])
    after = slice(120, None)

    def err(W, j):
        return np.sqrt(np.mean((W[after, j] - truth[after, j]) ** 2))

    assert err(S, 0) < 0.5 * err(P, 0)
    assert err(S, 1) < 1.02 * err(P, 1)


def test_noise_shrink_lets_go_while_the_face_moves_and_waits_for_its_warm_up():
    """No pull over the first ``warm_frames``; and when a well-seen direction jumps (a blink's onset) the pull on
    the others is let go, so a blink the fit spreads over a noisy direction keeps its peak."""
    Y, _ = _wander_and_signal()
    Y[600:606, 1] += 0.6  # a blink on the well-seen direction
    Y[600:606, 0] += 0.1  # ... part of it on the ill-seen one
    plain, shrunk = _shrink_pair(warm=60)
    P = np.array([plain.step(y) for y in Y])
    S = np.array([shrunk.step(y) for y in Y])
    np.testing.assert_array_equal(S[:60], P[:60])
    assert np.std(S[500:590, 0]) < 0.5 * np.std(P[500:590, 0])  # held at its mean before
    np.testing.assert_allclose(S[602:606, 0], P[602:606, 0], atol=0.02)  # let go during it


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.floats(0.5, 8.0))
def test_noise_shrink_output_lies_between_the_mean_and_the_imm(seed, c):
    """The pull is a gain in [0, 1] toward the running mean, per direction: never past the mean, never beyond
    the IMM's own output."""
    rng = np.random.default_rng(seed)
    Y = rng.normal(size=(80, 3)).cumsum(0) * rng.uniform(0.01, 1.0, 3) + rng.normal(0, 0.2, (80, 3))
    axes = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    plain = RotatedIMM(axes, IMMFilter(1e-4, 1e-2, 0.05))
    shrunk = RotatedIMM(axes, IMMFilter(1e-4, 1e-2, 0.05), NoiseShrink(c=c, warm_frames=5))
    for y in Y:
        x = axes.T @ plain.step(y)
        s = axes.T @ shrunk.step(y)
        m = shrunk.shrink.mean
        assert np.all((s - m) * (x - m) >= -1e-12)
        assert np.all(np.abs(s - m) <= np.abs(x - m) + 1e-12)


def test_noise_shrink_refuses_bad_settings():
    for kw in ({"c": 0.0}, {"warm_frames": 1}, {"half_life_frames": 0.0}):
        with pytest.raises(ValueError, match="NoiseShrink"):
            NoiseShrink(**kw)


def test_shared_move_lets_an_ill_seen_direction_follow_a_blink_the_well_seen_one_shows():
    """A blink moves a well-seen direction a lot and an ill-seen one a little (its step ~1 sd of its nominal
    noise): alone, the ill-seen one's hold model takes the step for noise and creeps; with the face's regime
    shared (``share``), it follows once the well-seen one is seen to move. Still, the two are the plain IMM."""
    rng = np.random.default_rng(4)
    T, onset = 300, 200
    truth = np.zeros((T, 2))
    truth[onset:, 0], truth[onset:, 1] = 0.08, 0.6
    Y = truth + rng.normal(0, [0.01, 0.005], (T, 2))
    q_hold, q_move = dwna_variance(0.5, 60.0), dwna_variance(80.0, 60.0)
    r = np.array([0.07**2, 0.005**2])

    def run(share):
        f = RotatedIMM(np.eye(2), IMMFilter(q_hold, q_move, r), share=share)
        return np.array([f.step(y) for y in Y])

    alone, shared = run(0.0), run(0.3)
    after = slice(onset, onset + 15)
    assert np.abs(shared[after, 0] - 0.08).mean() < 0.7 * np.abs(alone[after, 0] - 0.08).mean()  # 0.016, 0.025
    assert np.abs(shared[after, 1] - 0.6).mean() < 1.05 * np.abs(alone[after, 1] - 0.6).mean()
    np.testing.assert_allclose(shared[:onset - 10], alone[:onset - 10], atol=0.002)  # still face: as before
    with pytest.raises(ValueError, match="share"):
        RotatedIMM(np.eye(2), IMMFilter(q_hold, q_move, r), share=1.5)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.sampled_from([0.0, 0.3, 1.0]), st.integers(2, 12), st.booleans())
def test_the_weight_stage_in_one_call_is_its_three_parts_bit_for_bit(seed, share, warm, regional):
    """Streamed, RotatedIMM's IMM step, shared regime and pull run as one compiled call (issue 39, the merged main's
    p99); its output is the three parts' (IMMFilter.step, share_move, NoiseShrink.step) composed, bit for bit,
    with the noise changed in mid-stream as kalman does when its strength moves."""
    rng = np.random.default_rng(seed)
    m, T = 5, 40
    Y = rng.normal(size=(T, m)).cumsum(0) * rng.uniform(0.01, 1.0, m) + rng.normal(0, 0.2, (T, m))
    axes = np.linalg.qr(rng.normal(size=(m, m)))[0]
    r = rng.uniform(1e-4, 0.1, m)
    near = None
    if regional:  # the regime shared by how much the directions share markers (shared_markers)
        near = rng.uniform(0, 1, (m, m))
        near = (near + near.T) / 2
        np.fill_diagonal(near, 1.0)
    fused = RotatedIMM(axes, IMMFilter(1e-4, 1e-2, r), NoiseShrink(c=4.0, warm_frames=warm), share, near)
    imm, shrink = IMMFilter(1e-4, 1e-2, r), NoiseShrink(c=4.0, warm_frames=warm)
    for t, y in enumerate(Y):
        if t == T // 2:
            fused.set_noise(2 * r)
            imm.set_noise(2 * r)
        u = axes.T @ y
        before = np.zeros(m) if imm.move_probability is None else imm.move_probability.copy()
        x = imm.step(u)
        if t and share > 0:
            imm.share_move(share, x)
        want = axes @ shrink.step(u, before, x, imm.move_probability if t else np.zeros(m), near)
        np.testing.assert_array_equal(fused.step(y), want)


def test_shared_markers_is_one_for_the_same_markers_and_zero_for_disjoint_ones():
    """Two shapes moving markers 0-1 and one moving marker 2: the first two directions share all their markers
    whatever their mix, the third none."""
    B = np.zeros((9, 3))
    B[0:6, 0] = [1, 0, 0, 0, 2, 0]
    B[0:6, 1] = [0, 3, 0, 1, 0, 0]
    B[6:9, 2] = [0, 0, 1]
    axes = np.eye(3)
    near = shared_markers(B, axes)
    np.testing.assert_allclose(np.diag(near), 1.0)
    assert near[0, 2] == near[2, 0] == 0.0 and near[1, 2] == 0.0
    assert 0.0 < near[0, 1] < 1.0 and near[0, 1] == near[1, 0]  # both move markers 0 and 1, in other shares
    same = np.zeros((9, 2))
    same[0:6, 0], same[0:6, 1] = [1, 0, 0, 0, 2, 0], [2, 0, 0, 0, 4, 0]  # the same markers in the same shares
    np.testing.assert_allclose(shared_markers(same, np.eye(2)), 1.0)


def test_a_move_on_other_markers_does_not_let_a_directions_pull_go():
    """A well-seen direction jumps while an ill-seen one holds its noise. Let go by the face's largest 'move'
    probability (``near`` None), the ill-seen one's pull toward its mean is off whenever the other moves, so its noise
    comes through; with the two on disjoint markers (``near`` the identity) it stays pulled; with ``near`` all ones it
    is the face-wide let-go bit for bit."""
    rng = np.random.default_rng(7)
    T = 400
    Y = np.zeros((T, 2))
    truth = np.where(np.arange(T) % 40 < 20, 0.0, 0.5)  # speech: the mouth moves all the time
    Y[:, 0] = truth
    Y += rng.normal(0, [0.005, 0.05], (T, 2))
    q_hold, q_move = dwna_variance(0.5, 60.0), dwna_variance(80.0, 60.0)
    r = np.array([0.005**2, 0.05**2])

    def run(near):
        f = RotatedIMM(np.eye(2), IMMFilter(q_hold, q_move, r), NoiseShrink(warm_frames=30), 0.3, near)
        return np.array([f.step(y) for y in Y])

    face, regional, ones = run(None), run(np.eye(2)), run(np.ones((2, 2)))
    np.testing.assert_array_equal(face, ones)
    jit = [np.abs(np.diff(w[100:, 1], 2)).mean() for w in (face, regional)]
    assert jit[1] < 0.5 * jit[0]
    err = [np.sqrt(np.mean((w[100:, 0] - truth[100:]) ** 2)) for w in (face, regional)]
    assert err[1] < 1.1 * err[0]  # the mouth follows as well as before
