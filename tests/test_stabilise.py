"""Head stabilisation (Seol 2012 §3.1, Curio 2006 §2.3): Kabsch invariants, robustness, streams."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from livecap.calibration.stabilise import HeadStabiliser, head_pose_error, kabsch, robust_pose, smooth_pose


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(3, 30))
def test_kabsch_recovers_rigid_motion(seed, k):
    rng = np.random.default_rng(seed)
    src = rng.normal(0, 50, (k, 3))
    R = Rotation.random(random_state=seed).as_matrix()
    t = rng.normal(0, 500, 3)
    R_est, t_est = kabsch(src, src @ R.T + t)
    np.testing.assert_allclose(R_est, R, atol=1e-9)
    np.testing.assert_allclose(t_est, t, atol=1e-7)
    assert np.linalg.det(R_est) > 0


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 8))
def test_batched_kabsch_recovers_every_frame(seed, T):
    rng = np.random.default_rng(seed)
    src = rng.normal(0, 50, (6, 3))
    R = Rotation.random(T, random_state=seed).as_matrix()
    t = rng.normal(0, 500, (T, 3))
    dst = np.einsum("tij,kj->tki", R, src) + t[:, None]
    R_est, t_est = kabsch(src, dst)
    np.testing.assert_allclose(R_est, R, atol=1e-9)
    np.testing.assert_allclose(t_est, t, atol=1e-7)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.booleans())
def test_kabsch_never_reflects(seed, batched):
    rng = np.random.default_rng(seed)
    src = rng.normal(0, 1, (6, 3))
    dst = src * np.array([-1, 1, 1])  # a mirror image: the best rotation, not a reflection
    if batched:
        dst = np.stack([dst, rng.normal(0, 1, (6, 3))])
    R, _ = kabsch(src, dst)
    assert np.all(np.linalg.det(R) > 0.999999)
    np.testing.assert_allclose(np.einsum("...ji,...jk->...ik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)


def test_kabsch_with_no_weight_gives_identity_not_nan():
    R, t = kabsch(np.ones((4, 3)), np.ones((4, 3)), np.zeros(4))
    assert np.isfinite(R).all() and np.isfinite(t).all()


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(10, 80), st.integers(0, 5))
def test_robust_fit_ignores_one_jumping_stable_marker(seed, jump, which):
    rng = np.random.default_rng(seed)
    ref = rng.normal(0, 50, (6, 3))
    R = Rotation.random(random_state=seed).as_matrix()
    t = rng.normal(0, 300, 3)
    pts = ref @ R.T + t
    direction = rng.normal(size=3)
    pts[which] += jump * direction / np.linalg.norm(direction)
    R_est, t_est, w = robust_pose(ref, pts, np.ones(6, bool))
    np.testing.assert_allclose(R_est, R, atol=1e-6)
    assert w[which] == 0.0
    R_ls, _ = kabsch(ref, pts)
    assert np.abs(R_ls - R).max() > 10 * np.abs(R_est - R).max()  # the plain fit is dragged


def _rigid_take(T=20, n=12, seed=0):
    rng = np.random.default_rng(seed)
    ref = rng.normal(0, 50, (n, 3))
    stable = np.zeros(n, bool)
    stable[:5] = True
    Rs = Rotation.random(T, random_state=seed).as_matrix()
    ts = rng.normal(0, 100, (T, 3))
    pos = np.einsum("tij,nj->tni", Rs, ref) + ts[:, None]
    return ref, stable, Rs, ts, pos


def test_batched_stabilise_matches_per_frame_and_step():
    ref, stable, Rs, ts, pos = _rigid_take(T=6, n=10)
    valid = np.ones((6, 10), bool)
    valid[2, 0] = False
    valid[3, :4] = False  # only one stable marker left: falls back to all visible markers
    pos[4, 1] += 30.0  # a stable marker jumps
    stab = HeadStabiliser(ref, stable)
    local, R, t = stab.stabilise(pos, valid)
    np.testing.assert_allclose(R, Rs, atol=1e-7)
    ok = valid.copy()
    ok[4, 1] = False
    np.testing.assert_allclose(local[ok], np.broadcast_to(ref, local.shape)[ok], atol=1e-6)
    for i in range(6):
        li, Ri, _ = stab.stabilise(pos[i], valid[i])
        np.testing.assert_allclose(li, local[i], atol=1e-9)
        ls, Rstep, _ = stab.step(pos[i], valid[i])
        np.testing.assert_allclose(Rstep, R[i], atol=1e-9)
        np.testing.assert_allclose(ls, local[i], atol=1e-9)
    assert np.all(local[~valid] == 0.0)


def test_too_few_markers_hold_the_last_pose():
    ref, stable, Rs, ts, pos = _rigid_take(T=5)
    valid = np.ones(pos.shape[:2], bool)
    valid[2, 2:] = False  # two markers left
    pos[2, 2:] = np.nan
    stab = HeadStabiliser(ref, stable)
    R, t, ok = stab.pose_batch(np.nan_to_num(pos), valid)
    assert list(ok) == [True, True, False, True, True]
    np.testing.assert_allclose(R[2], Rs[1], atol=1e-9)
    for i in range(5):
        local, Ri, _ = stab.step(pos[i], valid[i])
        assert np.isfinite(local).all()
    stab.reset()
    local, Ri, _ = stab.step(pos[2], np.zeros(len(ref), bool))
    np.testing.assert_allclose(Ri, np.eye(3))
    assert np.all(local == 0)


def test_pose_convention_raw_is_R_stabilised_plus_t():
    ref, stable, Rs, ts, pos = _rigid_take(T=3)
    local, R, t = HeadStabiliser(ref, stable).stabilise(pos, np.ones(pos.shape[:2], bool))
    np.testing.assert_allclose(np.einsum("tij,tnj->tni", R, local) + t[:, None], pos, atol=1e-9)


def test_smooth_pose_keeps_motion_and_removes_jitter():
    T = 600
    time = np.arange(T) / 120
    rot = Rotation.from_euler("xyz", np.stack([10 * np.sin(time), 20 * np.sin(0.7 * time), 0 * time], 1),
                              degrees=True)
    t = np.stack([30 * np.sin(time), 0 * time, 5 * time], 1)
    rng = np.random.default_rng(0)
    noisy = rot * Rotation.from_rotvec(rng.normal(0, np.radians(0.5), (T, 3)))
    Rs, ts = smooth_pose(noisy.as_matrix(), t + rng.normal(0, 0.5, (T, 3)), 25)
    err_raw = (noisy * rot.inv()).magnitude()
    err_smooth = (Rotation.from_matrix(Rs) * rot.inv()).magnitude()
    assert err_smooth.mean() < 0.4 * err_raw.mean()
    assert np.abs(ts - t).mean() < 0.2


def test_head_pose_error_is_zero_for_the_truth_in_another_reference_frame():
    ref, stable, Rs, ts, pos = _rigid_take(T=4)
    A = Rotation.random(random_state=3).as_matrix()
    a = np.array([5.0, -20.0, 7.0])
    moved_ref = ref @ A.T + a  # our neutral lives in another frame than the truth's head frame
    R, t = HeadStabiliser(moved_ref, stable).pose(pos, np.ones(pos.shape[:2], bool))
    rot, tr = head_pose_error(R, t, Rs, ts, moved_ref, ref)
    assert rot.max() < 1e-5 and tr.max() < 1e-6


@pytest.mark.parametrize("missing", [1, 4])
def test_demo_take_with_stable_markers_missing_for_a_second_still_stabilises(demo, missing):
    from livecap.calibration.profile import calibrate, estimate_neutral
    from livecap.demo.performance import PerformanceSettings, perform

    rig, layout = demo
    perf = perform(rig, layout, PerformanceSettings(seconds=5, rate=60, stable_dropout=1.0, seed=3))
    take = perf.take
    stable = np.flatnonzero(layout.stable)
    span = slice(int(0.4 * take.n_frames), int(0.4 * take.n_frames) + 60)
    assert not take.valid[span, stable[0]].any()  # the generator's dropout is there
    take.valid[span, stable[:missing]] = False  # 4 missing: fewer than 3 stable, all markers used
    profile = calibrate(rig, layout, estimate_neutral(take, layout.stable, 60))
    R, t = profile.stabiliser().pose(take.positions, take.valid)
    rot, tr = head_pose_error(R, t, Rotation.from_quat(perf.head_rotation).as_matrix(), perf.head_translation,
                              profile.source_neutral, perf.actor_neutral)
    assert rot[span].max() < 2.0 and tr[span].max() < 3.0
    assert rot.mean() < 0.8 and tr.mean() < 1.2


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([1, 7, 47, 48, 300]), st.floats(0.0, 5.0))
def test_closed_form_rotation_is_the_svd_rotation(seed, B, noise):
    """Horn's quaternion (eigh for small batches, Newton on the quartic for large) = Kabsch by SVD."""
    from solvers.rigid import _svd_rotation, rotation_from_covariance

    rng = np.random.default_rng(seed)
    a = rng.normal(0, 50, (B, 6, 3))
    a -= a.mean(1, keepdims=True)
    R0 = Rotation.random(B, random_state=seed).as_matrix()
    b = np.einsum("bij,bkj->bki", R0, a) + rng.normal(0, noise, (B, 6, 3))
    b -= b.mean(1, keepdims=True)
    H = np.einsum("bki,bkj->bij", a, b)
    bound = 0.5 * ((a * a).sum((1, 2)) + (b * b).sum((1, 2)))
    np.testing.assert_allclose(rotation_from_covariance(H, bound), _svd_rotation(H), atol=1e-11)


def test_closed_form_rotation_handles_degenerate_sets():
    """Mirror images, collinear points and no weight go to the SVD's answer, never NaN."""
    from solvers.rigid import _svd_rotation, rotation_from_covariance

    rng = np.random.default_rng(3)
    src = rng.normal(0, 1, (6, 3))
    line = np.outer(np.arange(6.0), [1.0, 2.0, 3.0])
    cases = [(src, src * [-1, 1, 1]), (line, line @ Rotation.random(random_state=1).as_matrix().T),
             (np.zeros((6, 3)), np.zeros((6, 3)))]
    for x, y in cases:
        x, y = x - x.mean(0), y - y.mean(0)
        H = np.repeat((x.T @ y)[None], 60, axis=0)
        bound = np.full(60, 0.5 * ((x * x).sum() + (y * y).sum()))
        for R in (rotation_from_covariance(H[:1]), rotation_from_covariance(H, bound)):
            assert np.isfinite(R).all()
            np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)
            np.testing.assert_allclose(R, _svd_rotation(H[: len(R)]), atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(3, 12), st.floats(0.0, 40.0))
def test_streamed_fit_with_deleted_residuals_matches_the_batched_form(seed, k, jump):
    """The shared-products fit and leave-one-out residuals equal plain Kabsch fits, one per marker left out."""
    from livecap.calibration.stabilise import LEAVE_ONE_OUT_MAX, _fit_with_deleted, _residuals

    rng = np.random.default_rng(seed)
    ref = rng.normal(0, 50, (k, 3))
    pts = ref @ Rotation.random(random_state=seed).as_matrix().T + rng.normal(0, 800, 3)
    pts += rng.normal(0, 0.5, (k, 3))
    pts[rng.integers(k)] += jump
    use = rng.random(k) > 0.2
    use[:3] = True
    R, t, r, Rall, tall = _fit_with_deleted(ref, pts, use)
    R0, t0 = kabsch(ref, pts, use)
    np.testing.assert_allclose(R, R0, atol=1e-10)
    np.testing.assert_allclose(t, t0, atol=1e-8)
    loo = 5 <= k <= LEAVE_ONE_OUT_MAX
    assert Rall.shape == (k + 1 if loo else 1, 3, 3) and tall.shape == (len(Rall), 3)
    np.testing.assert_allclose(Rall[0], R0, atol=1e-10)
    np.testing.assert_allclose(tall[0], t0, atol=1e-8)
    expected = _residuals(ref, pts, R0, t0)
    for j in np.flatnonzero(use) if loo and use.sum() >= 5 else []:
        others = use & (np.arange(k) != j)
        Rj, tj = kabsch(ref[others], pts[others])
        expected[j] = max(expected[j], np.linalg.norm(Rj @ ref[j] + tj - pts[j]))
        np.testing.assert_allclose(Rall[j + 1], Rj, atol=1e-9)  # IRLS's candidate starts
        np.testing.assert_allclose(tall[j + 1], tj, atol=1e-7)
    np.testing.assert_allclose(r[use], expected[use], atol=1e-8)
    Rb, tb, rb, _, _ = _fit_with_deleted(ref, np.stack([pts, pts + 1.0]), np.stack([use, use]))  # a take at once
    np.testing.assert_allclose(Rb, [R, R], atol=1e-10)
    np.testing.assert_allclose(tb, [t, t + 1.0], atol=1e-8)
    np.testing.assert_allclose(rb[:, use], [r[use], r[use]], atol=1e-8)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 12), st.integers(1, 4), st.integers(0, 40))
def test_savgol_matches_scipy(seed, half, order, extra):
    """The numpy Savitzky-Golay filter equals scipy.signal.savgol_filter (mode interp) on any signal."""
    from scipy.signal import savgol_filter

    from livecap.calibration.stabilise import savgol

    window = 2 * half + 1
    if order >= window:
        return
    x = np.random.default_rng(seed).normal(0, 300, (window + extra, 4))
    np.testing.assert_allclose(savgol(x, window, order), savgol_filter(x, window, order, axis=0), atol=1e-9)


def _per_frame_step(stab, pos, valid):
    """The streamed step as it was before ``FrameFit``: ``robust_pose`` on the frame's stable markers."""
    R_last, t_last = np.eye(3), np.zeros(3)
    out = []
    k = np.flatnonzero(stab.stable)
    for p, v in zip(pos, valid, strict=True):
        v = v & np.isfinite(p).all(-1)
        if v[k].sum() >= 3:
            R_last, t_last, _ = robust_pose(stab.reference[k], np.where(v[k, None], p[k], 0.0), v[k],
                                            stab.iterations, stab.floor_mm)
        elif v.sum() >= 3:
            R_last, t_last, _ = robust_pose(stab.reference, np.where(v[:, None], p, 0.0), v, stab.iterations,
                                            stab.floor_mm)
        out.append((R_last, t_last))
    return out


@settings(max_examples=400, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(3, 12), st.floats(0.0, 25.0), st.floats(0.0, 1.5),
       st.integers(0, 3))
def test_frame_fit_equals_robust_pose(seed, k, jump, noise, missing):
    """The prepared single-frame fit takes the same check and returns the same pose as ``robust_pose``."""
    from livecap.calibration.stabilise import FrameFit

    rng = np.random.default_rng(seed)
    ref = rng.normal(0, 50, (k, 3))
    fit = FrameFit(ref, 3, 1.0)
    for _ in range(3):  # a mask seen again comes from the cache
        pts = ref @ Rotation.random(random_state=rng.integers(2**32)).as_matrix().T + rng.normal(0, 800, 3)
        pts += rng.normal(0, noise, (k, 3))
        pts[rng.integers(k)] += jump * rng.normal(size=3) / np.sqrt(3)
        use = np.ones(k, bool)
        use[rng.choice(k, min(missing, k - 3), replace=False)] = False
        pts[~use] = rng.choice([0.0, np.nan])
        R, t, w = fit.fit(pts, use)
        R0, t0, w0 = robust_pose(ref, np.where(use[:, None], pts, 0.0), use)
        # nearly collinear markers amplify either path's rounding (three of them 0.1 mm off a line: ~3e-9 mm)
        s = np.linalg.svd(ref[use] - ref[use].mean(0), compute_uv=False)
        tol = 1e-9 * max(1.0, 0.05 * s[0] / s[1])
        np.testing.assert_allclose(R, R0, rtol=0, atol=tol)
        np.testing.assert_allclose(t, t0, rtol=0, atol=tol)
        np.testing.assert_allclose(w, w0, rtol=0, atol=tol)


def test_frame_fit_cache_keeps_the_prepared_sets_when_full():
    """Many visibility sets (8 stable markers, random gaps) overflow the cache: the oldest others leave,
    the all-seen and one-missing sets stay, and every pose still equals ``robust_pose``'s."""
    from livecap.calibration.stabilise import FrameFit

    rng = np.random.default_rng(3)
    k = 8
    ref = rng.normal(0, 50, (k, 3))
    fit = FrameFit(ref, 3, 1.0)
    kept = list(fit._masks)
    for _ in range(300):
        use = rng.random(k) > 0.4
        use[rng.choice(k, 3, replace=False)] = True
        pts = ref @ Rotation.random(random_state=rng.integers(2**32)).as_matrix().T + rng.normal(0, 0.3, (k, 3))
        R, t, _ = fit.fit(pts, use)
        R0, t0, _ = robust_pose(ref, np.where(use[:, None], pts, 0.0), use)
        np.testing.assert_allclose(R, R0, atol=1e-9)
        np.testing.assert_allclose(t, t0, atol=1e-9)
        assert len(fit._masks) <= FrameFit.CACHE
    assert len(kept) == k + 1 and all(key in fit._masks for key in kept)


def test_frame_fit_degenerate_stable_markers_match_robust_pose():
    """Collinear or coincident stable markers (a top eigenvalue near double) take ``robust_pose``'s own path."""
    from livecap.calibration.stabilise import FrameFit

    line = np.outer(np.arange(6.0), [10.0, 20.0, 30.0])
    R1 = Rotation.random(random_state=1).as_matrix()
    for ref, pts in ((line, line @ R1.T + 5.0), (np.zeros((6, 3)), np.ones((6, 3)))):
        use = np.ones(6, bool)
        R, t, w = FrameFit(ref).fit(pts, use)
        R0, t0, _ = robust_pose(ref, pts, use)
        assert np.isfinite(R).all() and np.isfinite(t).all()
        np.testing.assert_allclose(R, R0, atol=1e-9)
        np.testing.assert_allclose(t, t0, atol=1e-9)


def test_streamed_head_fit_equals_the_per_frame_robust_pose_on_a_take_with_outliers():
    """Jumps of 5-20 mm, a stable marker missing (zeros or NaN), < 3 stable (fallback), none (hold)."""
    rng = np.random.default_rng(7)
    T, n = 120, 14
    ref = rng.normal(0, 50, (n, 3))
    stable = np.zeros(n, bool)
    stable[:6] = True
    Rs = Rotation.random(T, random_state=7).as_matrix()
    pos = np.einsum("tij,nj->tni", Rs, ref) + rng.normal(0, 300, (T, 3))[:, None] + rng.normal(0, 0.4, (T, n, 3))
    pos[10:14, 2] += [5.0, 0.0, 0.0]
    pos[20:23, 4] += [0.0, -12.0, 8.0]
    pos[30:33, 0] += [20.0, 0.0, 0.0]
    valid = np.ones((T, n), bool)
    valid[40:50, 1] = False
    pos[40:45, 1] = 0.0
    pos[45:50, 1] = np.nan
    valid[60:65, 1:6] = False  # one stable marker left: every visible marker fits
    pos[60:65, 1:6] = 0.0
    valid[70:73] = False  # nothing: hold
    pos[70:73] = np.nan
    stab = HeadStabiliser(ref, stable)
    expected = _per_frame_step(stab, pos, valid)
    Rb, tb, ok = stab.pose_batch(np.nan_to_num(pos), valid)
    for i in range(T):
        local, R, t = stab.step(pos[i], valid[i])
        np.testing.assert_allclose(R, expected[i][0], rtol=0, atol=1e-9)
        np.testing.assert_allclose(t, expected[i][1], rtol=0, atol=1e-9)
        np.testing.assert_allclose(R, Rb[i], rtol=0, atol=1e-9)
        np.testing.assert_allclose(t, tb[i], rtol=0, atol=1e-9)
        assert np.isfinite(local).all() and np.all(local[~valid[i]] == 0.0)
    assert not ok[70:73].any() and ok[:70].all()


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(3, 12), st.floats(0.0, 25.0), st.floats(0.0, 1.5),
       st.integers(0, 3))
def test_compiled_check_equals_the_numpy_check(seed, k, jump, noise, missing):
    """The compiled check (Jacobi eigenvectors) takes the numpy check's outcome, with the same fits to rounding."""
    from livecap.calibration.stabilise import FrameFit
    from solvers import rigid_kernels
    from solvers.rigid import DEGENERATE, ROTATION_MAP
    from tests.head_fit_reference import check_fit

    rng = np.random.default_rng(seed)
    ref = rng.normal(0, 50, (k, 3))
    fit = FrameFit(ref, 3, 1.0)
    pts = ref @ Rotation.random(random_state=rng.integers(2**32)).as_matrix().T + rng.normal(0, 800, 3)
    pts += rng.normal(0, noise, (k, 3))
    pts[rng.integers(k)] += jump * rng.normal(size=3) / np.sqrt(3)
    use = np.ones(k, bool)
    use[rng.choice(k, min(missing, k - 3), replace=False)] = False
    left, Wn, Q, ((Zc, Lc), _), _, cs, _ = fit._prepare(use)
    P = pts[left]
    got = rigid_kernels.check_fit(P, Wn, Q, Zc, Lc, cs, ROTATION_MAP, 3.0, DEGENERATE)
    want = check_fit(P, Wn, Q, Zc, Lc, cs)
    d = (want[3].reshape(-1) @ Zc + Lc @ want[4]).reshape(-1, 3)
    if abs(np.sqrt((d * d).sum(1)).max() - 3.0) < 1e-9:
        return  # on the threshold itself rounding may decide either way
    assert got[0] == want[0]
    np.testing.assert_allclose(got[3], want[3], rtol=0, atol=1e-11)  # q q^T: the sign of q drops out
    np.testing.assert_allclose(got[4], want[4], rtol=0, atol=1e-9)  # the centroid's sum in another order (mm)
    np.testing.assert_allclose(got[5], want[5], rtol=0, atol=1e-9)
    if want[0] == rigid_kernels.PASSED:
        np.testing.assert_allclose(got[1], want[1], rtol=0, atol=1e-11)  # 1.08e-12 seen, noiseless
        np.testing.assert_allclose(got[2], want[2], rtol=0, atol=1e-9)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(1e-6, 1e6))
def test_jacobi_top_eigenpair_equals_lapacks(seed, scale):
    """The kernel's 4 x 4 Jacobi: the largest two eigenvalues and the top eigenvector of ``numpy.linalg.eigh``."""
    from solvers.rigid_kernels import _top_two

    rng = np.random.default_rng(seed)
    A = rng.normal(0, scale, (4, 4))
    A = A + A.T
    ev, V = np.linalg.eigh(A)
    q = np.empty(4)
    top, second = _top_two(A.copy(), q)
    np.testing.assert_allclose([top, second], ev[[3, 2]], rtol=0, atol=1e-12 * np.abs(ev).max())
    if ev[3] - ev[2] > 1e-6 * np.abs(ev).max():
        assert abs(abs(q @ V[:, 3]) - 1.0) < 1e-12 * np.abs(ev).max() / (ev[3] - ev[2]) + 1e-15


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(3, 12), st.floats(4.0, 40.0), st.floats(0.0, 1.5),
       st.integers(0, 3), st.integers(1, 3))
def test_compiled_refit_equals_the_numpy_refit(seed, k, jump, noise, missing, jumps):
    """A frame that fails the check: the compiled start and IRLS give the numpy reference's pose and weights."""
    from livecap.calibration.stabilise import MAD_TO_SIGMA, TUKEY_C, FrameFit
    from solvers import rigid_kernels
    from solvers.rigid import DEGENERATE, ROTATION_MAP
    from tests.head_fit_reference import refit

    rng = np.random.default_rng(seed)
    ref = rng.normal(0, 50, (k, 3))
    fit = FrameFit(ref, 3, 1.0)
    pts = ref @ Rotation.random(random_state=rng.integers(2**32)).as_matrix().T + rng.normal(0, 800, 3)
    pts += rng.normal(0, noise, (k, 3))
    pts[rng.choice(k, min(jumps, k), replace=False)] += jump * rng.normal(size=(min(jumps, k), 3)) / np.sqrt(3)
    use = np.ones(k, bool)
    use[rng.choice(k, min(missing, k - 3), replace=False)] = False
    left, Wn, Q, ((Zc, Lc), Z), _, cs, _ = fit._prepare(use)
    P = pts[left]
    _, _, _, o, p, cb = rigid_kernels.check_fit(P, Wn, Q, Zc, Lc, cs, ROTATION_MAP, 3.0, DEGENERATE)
    R, t, w = rigid_kernels.refit(ref[left], P, o, p, cb, Wn, Z, cs, ROTATION_MAP, 3, 1.0, TUKEY_C, MAD_TO_SIGMA)
    R0, t0, w0 = refit(ref[left], P, o, p, cb, Wn, Z, cs)
    # a Tukey weight at its cut-off (or a median tie in the start's score) may go either way by rounding
    s = np.linalg.svd(ref[left] - ref[left].mean(0), compute_uv=False)
    tol = 1e-9 * max(1.0, 0.05 * s[0] / s[1])
    if np.abs(w - w0).max() > 1e-6:
        return
    np.testing.assert_allclose(R, R0, rtol=0, atol=tol)
    np.testing.assert_allclose(t, t0, rtol=0, atol=tol)
    np.testing.assert_allclose(w, w0, rtol=0, atol=tol)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 80), st.floats(0.0, 1.0))
def test_compiled_unrotate_equals_numpy(seed, n, seen):
    """The streamed step's stabilised markers: ``(positions - t) @ R``, 0 where not valid (NaN there too)."""
    from solvers.rigid_kernels import unrotate

    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=rng.integers(2**32)).as_matrix()
    t = rng.normal(0, 500, 3)
    pos = rng.normal(0, 500, (n, 3))
    valid = rng.random(n) < seen
    pos[~valid] = rng.choice([0.0, np.nan])
    want = (pos - t) @ R
    want[~valid] = 0.0
    np.testing.assert_allclose(unrotate(pos, valid, R, t), want, rtol=0, atol=1e-10)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(3, 14), st.integers(8, 40), st.floats(0.0, 40.0))
def test_the_compiled_take_check_equals_the_numpy_batch(seed, k, T, jump):
    """A take's fits, leave-one-out fits and residuals (solvers.rigid_take_kernels) equal the numpy batch's, frames with
    jumps, missing markers, too few markers and degenerate (collinear, coincident) sets included."""
    from livecap.calibration.stabilise import COMPILED_MIN_FRAMES, _fit_with_deleted, _fit_with_deleted_batch

    rng = np.random.default_rng(seed)
    ref = rng.normal(0, 50, (k, 3))
    R = Rotation.random(T, random_state=seed).as_matrix()
    pts = np.einsum("tij,kj->tki", R, ref) + rng.normal(0, 800, (T, 1, 3)) + rng.normal(0, 0.5, (T, k, 3))
    pts[np.arange(T), rng.integers(k, size=T)] += jump
    use = rng.random((T, k)) > 0.2
    use[:, :3] = True  # three or more in use, as the stabiliser asks of a fit
    use[0, 2:] = False  # but for one frame: too few markers
    line = ref[0] + np.outer(np.arange(k), [1.0, 2.0, 3.0])  # collinear markers
    pts[1] = line + rng.normal(0, 1e-9, (k, 3))
    pts[2] = pts[2, 0]  # every marker at one point
    assert T >= COMPILED_MIN_FRAMES
    compiled, batch = _fit_with_deleted(ref, pts, use), _fit_with_deleted_batch(ref, pts, use)
    rows = np.arange(3, T)  # the degenerate frames above take either path's rounding of an ill-posed rotation
    for a, b, tol in zip(compiled[:3], batch[:3], (1e-9, 1e-6, 1e-6), strict=True):
        assert a.shape == b.shape and np.isfinite(a).all()
        np.testing.assert_allclose(a[rows], b[rows], atol=tol)
    n = use.sum(1)[:, None] - np.concatenate([np.zeros((T, 1), int), use], axis=1)[:, :len(compiled[3][0])]
    posed = n[rows] >= 3  # a leave-one-out fit of fewer than 3 markers has no rotation to agree on (nor is it used)
    for a, b, tol in zip(compiled[3:], batch[3:], (1e-9, 1e-6), strict=True):
        assert a.shape == b.shape and np.isfinite(a).all()
        np.testing.assert_allclose(a[rows][posed], b[rows][posed], atol=tol)
