"""The marker-space box QP (solvers/marker_space_qp.py): the KKT conditions and the dense solve's optimum, alone
and as FrameQP's path where the shapes far outnumber the marker coordinates."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

import solvers.qp as qp_module
from solvers.box_qp import BoxQP
from solvers.marker_space_qp import MarkerSpaceQP
from solvers.pose_refine import RigidColumns
from solvers.qp import FrameQP


def _problem(rng, r: int, n: int, p: int, dmin: float = 1e-3):
    """r rows, n bounded weights (some limits infinite), p unpenalised unbounded columns (a pose)."""
    J = rng.normal(0, 2, (r, n + p))
    d = np.r_[rng.uniform(dmin, 2, n), np.zeros(p)]
    lo = np.r_[np.where(rng.random(n) < 0.1, -np.inf, rng.uniform(-1, 0, n)), np.full(p, -np.inf)]
    hi = np.r_[np.where(rng.random(n) < 0.1, np.inf, rng.uniform(0.1, 1.5, n)), np.full(p, np.inf)]
    f = rng.normal(0, 4, n + p)
    return J, d, lo, hi, f


def _kkt(H, f, lo, hi, x, tol):
    g = H @ x + f
    scale = tol * (1 + np.abs(H).max() * (1 + np.abs(x).max()) + np.abs(f).max())
    assert np.all(x >= lo) and np.all(x <= hi)
    free = (x > lo) & (x < hi)
    assert np.abs(g[free]).max(initial=0) <= scale
    assert np.all(g[(x == lo) & ~free] >= -scale) and np.all(g[(x == hi) & ~free] <= scale)


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), r=st.integers(3, 24), n=st.integers(1, 60), p=st.integers(0, 3),
       warm=st.booleans())
def test_kkt_and_the_dense_optimum(seed, r, n, p, warm):
    rng = np.random.default_rng(seed)
    J, d, lo, hi, f = _problem(rng, r, n, p)
    H = np.diag(d) + J.T @ J
    try:
        q = MarkerSpaceQP(J, d, lo, hi, max_iter=5000)
    except np.linalg.LinAlgError:
        assert p and np.linalg.matrix_rank(J[:, n:]) < p  # refused only where the rows do not fix the pose
        return
    x0 = np.clip(rng.normal(0, 1, n + p), lo, hi) if warm else np.clip(np.zeros(n + p), lo, hi)
    x = q.solve(f, x0)
    assert x is not None, "no convergence"
    _kkt(H, f, lo, hi, x, 1e-9)
    np.testing.assert_allclose(x, BoxQP(H, lo, hi).solve(f), atol=1e-7)


def test_kept_factor_over_a_sequence_of_solves(monkeypatch):
    """Many frames on one pattern: the marker-space matrix updated by the changed columns, refreshed every REFRESH
    updates, gives each frame's optimum."""
    import solvers.marker_space_qp as msq

    monkeypatch.setattr(msq, "REFRESH", 16)  # refreshed several times in these frames
    rng = np.random.default_rng(7)
    J, d, lo, hi, f = _problem(rng, 18, 90, 6, dmin=0.1)  # a ridge: a weak one lets block pivoting cycle longer
    lo[:90], hi[:90] = 0.0, 1.0
    H = np.diag(d) + J.T @ J
    q = MarkerSpaceQP(J, d, lo, hi)
    box = BoxQP(H, lo, hi)
    x = np.clip(np.zeros(96), lo, hi)
    passes = []
    for _ in range(200):  # frames: one signal, fresh noise
        g = f + rng.normal(0, 1.0, 96)
        x = q.solve(g, x)
        passes.append(q.iterations)
        np.testing.assert_allclose(x, box.solve(g), atol=1e-8)
    assert max(passes) > 1


def test_bounded_column_without_curvature_refused():
    with pytest.raises(ValueError, match="unbounded"):
        MarkerSpaceQP(np.ones((3, 2)), np.array([1.0, 0.0]), np.zeros(2), np.ones(2))


def _rig(n_markers: int, m: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    neutral = rng.normal(0, 40, (n_markers, 3))
    B = rng.normal(0, 2, (3 * n_markers, m))
    pose = RigidColumns(neutral)
    return pose.augment(B, np.zeros(m), np.ones(m), np.zeros(m), np.eye(m)), rng

def _moving_frames(B: np.ndarray, rng: np.random.Generator, n: int, low: float):
    """n frames of 8 markers whose 80 weights wander (a random walk from U(low, 0.6)), ~15 % of markers hidden."""
    w_true = rng.uniform(low, 0.6, 80)
    for _ in range(n):
        w_true = np.clip(w_true + rng.normal(0, 0.1, 80), -0.2, 1.2)
        yield (B[:, :80] @ w_true + rng.normal(0, 0.3, 24)).reshape(8, 3), rng.random(8) > 0.15



@pytest.mark.parametrize("strength", [1e-2, 1.0])
def test_frameqp_marker_space_path_equals_weight_space(monkeypatch, strength):
    """kalman's fit at many shapes (pose columns, a ridge prior, markers dropping out): the same weights through
    the marker-space path as through the weight-space one."""
    (B, lo, hi, mean, P), rng = _rig(8, 80)
    fast = FrameQP(B, lo, hi, prior=(mean, P), prior_weight=strength)
    monkeypatch.setattr(qp_module, "MARKER_SPACE_RATIO", np.inf)
    slow = FrameQP(B, lo, hi, prior=(mean, P), prior_weight=strength)
    assert fast.marker_space and not slow.marker_space
    used = 0
    for s, seen in _moving_frames(B, rng, 60, 0.0):
        a, b = fast.step(s, seen), slow.step(s, seen)
        np.testing.assert_allclose(a, b, atol=1e-7)
        used += int(np.count_nonzero((a > lo) & (a < hi)) >= 24)
    assert used > 20  # the marker-space path really ran
    assert any(ws.marker_space for ws in fast._models.values())


def test_small_rigs_keep_the_weight_space_path():
    (B, lo, hi, mean, P), _ = _rig(20, 50)  # 60 marker coordinates, 56 columns: as ICT (~53 shapes) or 72 x 150
    assert not FrameQP(B, lo, hi, prior=(mean, P), prior_weight=1.0).marker_space


def test_prepare_builds_every_seen_patterns_marker_space_solver():
    (B, lo, hi, mean, P), _ = _rig(8, 80)
    qp = FrameQP(B, lo, hi, prior=(mean, P), prior_weight=1.0)
    for drop in range(3):
        seen = np.ones(8, bool)
        seen[drop] = False
        qp.step(np.zeros((8, 3)), seen)
    assert all(ws.marker_space is None for ws in qp._models.values())  # zero weights free: not taken yet
    qp.prepare_marker_space()
    assert len(qp._models) == 3 and all(isinstance(ws.marker_space, MarkerSpaceQP) for ws in qp._models.values())


def _counting(monkeypatch, name: str) -> list:
    """Calls of the module's ``name`` (a LAPACK routine) counted."""
    import solvers.marker_space_qp as msq

    calls, fn = [], getattr(msq, name)
    monkeypatch.setattr(msq, name, lambda *a, **k: calls.append(1) or fn(*a, **k))
    return calls


def test_a_few_changed_columns_are_solved_through_the_kept_factor(monkeypatch):
    """S of a free set <= WOODBURY columns from the kept factor's: S^-1 b by Woodbury, equal to the dense solve,
    and no refactor (a 216 x 216 Cholesky is ~0.2 ms, most of a late pass at 72 x 1000)."""
    from solvers.marker_space_qp import WOODBURY

    rng = np.random.default_rng(3)
    J, d, lo, hi, _ = _problem(rng, 12, 60, 0, dmin=0.1)
    q = MarkerSpaceQP(J, d, lo, hi)
    F = rng.random(60) < 0.5
    b = rng.normal(0, 1, 12)
    q._solve_S(F, b)  # factor kept for F
    refactors = _counting(monkeypatch, "dpotrf")
    for k in (1, 3, WOODBURY):
        G = F.copy()
        G[rng.choice(60, k, replace=False)] ^= True
        S = np.eye(12) + (J[:, G] / d[G]) @ J[:, G].T
        np.testing.assert_allclose(q._solve_S(G, b), np.linalg.solve(S, b), rtol=1e-10, atol=1e-12)
    assert not refactors
    G = F.copy()
    G[:WOODBURY + 1] ^= True
    S = np.eye(12) + (J[:, G] / d[G]) @ J[:, G].T
    np.testing.assert_allclose(q._solve_S(G, b), np.linalg.solve(S, b), rtol=1e-10, atol=1e-12)
    assert len(refactors) == 1


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), passes=st.integers(0, 6), p=st.integers(0, 3), now=st.integers(0, 7))
@example(seed=307227873, passes=0, p=0, now=7)  # the kept factor's rounding differs from a fresh solver's by 1.2e-14
def test_a_begun_solve_continues_to_the_same_x(seed, passes, p, now):
    """``begin`` runs the first passes (of them only ``now``, and the next one's factor; 7: all), ``solve`` of the
    same f and x0 runs the rest: the x of one whole solve, bit for bit, in as many passes; another f is solved from
    scratch (its x equal to a fresh solver's up to rounding: the solver keeps the factor of its last free set,
    updated by rank-k products, so the digits may differ)."""
    rng = np.random.default_rng(seed)
    J, d, lo, hi, f = _problem(rng, 12, 50, p)
    x0 = np.clip(rng.normal(0, 1, 50 + p), lo, hi)
    whole, split = MarkerSpaceQP(J, d, lo, hi), MarkerSpaceQP(J, d, lo, hi)
    x = whole.solve(f, x0)
    split.begin(f, x0, passes, now=min(now, passes) if now < 7 else None)
    np.testing.assert_array_equal(split.solve(f, x0), x)
    assert split.iterations == whole.iterations
    g = f + rng.normal(0, 1, 50 + p)
    split.begin(f, x0, passes)
    np.testing.assert_allclose(split.solve(g, x0), MarkerSpaceQP(J, d, lo, hi).solve(g, x0), rtol=0, atol=1e-10)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), r=st.integers(3, 24), n=st.integers(1, 60), p=st.integers(0, 3),
       same=st.booleans())
def test_the_data_term_from_the_projected_j_is_j_given_transposed_times_v(seed, r, n, p, same):
    """MarkerSpaceQP.data_term(v): J'v for J as given, read from the J with the pose projected off (and, built
    ``same`` as another strength's solver, from that one's arrays)."""
    rng = np.random.default_rng(seed)
    J, d, lo, hi, _ = _problem(rng, r, n, p)
    try:
        q = MarkerSpaceQP(J, d, lo, hi)
        if same:
            q = MarkerSpaceQP(J, 2.0 * d, lo, hi, same=q)
    except np.linalg.LinAlgError:
        return
    v = rng.normal(0, 3, r)
    want = J.T @ v
    np.testing.assert_allclose(q.data_term(v), want, rtol=0, atol=1e-9 * (1 + np.abs(J).max() * np.abs(v).sum()))


def test_frameqp_begin_then_step_equals_step():
    """A trial begun on one frame (FrameQP.begin) and stepped on the next gives the weights of the step alone."""
    (B, lo, hi, mean, P), rng = _rig(8, 80)
    a, b = (FrameQP(B, lo, hi, prior=(mean, P), prior_weight=1e-2) for _ in range(2))
    begun = 0
    for s, seen in _moving_frames(B, rng, 30, 0.2):
        begun += a.begin(s, seen, 1)
        np.testing.assert_array_equal(a.step(s, seen), b.step(s, seen))
    assert begun > 5


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), r=st.integers(3, 24), n=st.integers(1, 60), p=st.integers(0, 3),
       passes=st.integers(1, 3))
def test_bounded_solves_carry_their_partition_to_the_optimum(seed, r, n, p, passes):
    """frame_passes: a solve stops after that many passes at a feasible point and the next solve from it goes on
    from the partition it stopped at, so that solving the same QP again and again (a still actor) reaches the
    exact solve's optimum, KKT and all; a settled solve is the exact one."""
    _bounded_solves(seed, r, n, p, passes)


def _settle(q, H, f, x, passes):
    """Bounded solves of the same QP, each from the last one's x, until the KKT conditions hold: each stops after
    its passes, but the one where a block-pivoting cycle went to the primal method (which runs to the optimum)."""
    from solvers.marker_space_qp import FRESH_PASSES

    for call in range(300):
        x = q.solve(f, x, passes)
        assert np.all(x >= q.limits[0]) and np.all(x <= q.limits[1])
        try:
            _kkt(H, f, *q.limits, x, 1e-9)
            return x
        except AssertionError:
            assert q.iterations <= (max(passes, FRESH_PASSES) if call == 0 else passes)
    pytest.fail("300 bounded solves did not reach the optimum")


def _bounded_solves(seed, r, n, p, passes):
    rng = np.random.default_rng(seed)
    J, d, lo, hi, f = _problem(rng, r, n, p, dmin=0.05)
    H = np.diag(d) + J.T @ J
    try:
        q = MarkerSpaceQP(J, d, lo, hi, max_iter=5000)
    except np.linalg.LinAlgError:
        return
    q.limits = (lo, hi)
    x = _settle(q, H, f, np.clip(np.zeros(n + p), lo, hi), passes)
    g = f + rng.normal(0, 4, n + p)  # the next frames' data (a still actor)
    y = _settle(q, H, g, x, passes)
    assert np.all(y >= lo) and np.all(y <= hi)
    np.testing.assert_allclose(y, BoxQP(H, lo, hi).solve(g), atol=1e-7)


def test_a_bounded_solve_from_another_start_does_not_take_the_carried_partition(monkeypatch):
    """The carried partition belongs to the x the solve returned: from any other start (a strength switch warms
    the fit from another QP's x) the partition is the start's own and the solve the exact one."""
    rng = np.random.default_rng(5)
    J, d, lo, hi, f = _problem(rng, 12, 60, 0, dmin=0.1)
    a, b = MarkerSpaceQP(J, d, lo, hi), MarkerSpaceQP(J, d, lo, hi)
    x = a.solve(f + rng.normal(0, 3, 60), a.solve(f, np.clip(np.zeros(60), lo, hi), 1), 1)
    assert a.iterations == 1 and a._carry is not None  # one pass from its own stop
    start = np.clip(rng.normal(0, 1, 60), lo, hi)
    np.testing.assert_allclose(a.solve(f, start, 1), b.solve(f, start, 1), rtol=0, atol=1e-10)
    assert not np.array_equal(x, start)


def test_a_bounded_solve_runs_fresh_passes_from_another_start_and_frame_passes_from_its_own_stop(monkeypatch):
    """From a start that is not its own last stop (another pattern's or strength's x: its clipped point holds the
    weights its last pass freed at their limits) a solve runs FRESH_PASSES; the next frame's from the x it returned,
    frame_passes, from the partition that stop chose (not the clipped point's)."""
    import solvers.marker_space_qp as msq

    rng = np.random.default_rng(11)
    J, d, lo, hi, f = _problem(rng, 12, 60, 0, dmin=0.1)
    q = MarkerSpaceQP(J, d, lo, hi)
    x = q.solve(f, np.clip(np.zeros(60), lo, hi), 1)
    assert q.iterations == msq.FRESH_PASSES
    calls = []
    sub = q._subproblem
    monkeypatch.setattr(q, "_subproblem", lambda fG, a, b: calls.append((a.copy(), b.copy())) or sub(fG, a, b))
    g = f + rng.normal(0, 3, 60)  # the next frame's data
    y = q.solve(g, x, 1)
    assert q.iterations == 1 and q._carry is not None and q._carry[0] is y
    xG = x[q.G]
    assert not (np.array_equal(calls[0][0], xG <= lo) and np.array_equal(calls[0][1], xG >= hi))  # the stop's own


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(10, 70), p=st.integers(0, 3),
       scale=st.sampled_from([1e-2, 0.3, 3.0, 100.0]))
def test_a_switch_starts_from_the_peers_stop_and_partition_in_one_pass(seed, n, p, scale):
    """kalman's strength switch: this QP at another scale of D on the very rows of a peer, from the peer's stop,
    runs one pass from the partition that stop chose (not FRESH_PASSES from its clipped point), its S the peer's;
    bounded solves from its own stops then reach the optimum. A peer on more rows (a held-out trial) is not so
    taken: FRESH_PASSES from the clipped point."""
    import solvers.marker_space_qp as msq

    rng = np.random.default_rng(seed)
    r = 12
    J, d, lo, hi, f = _problem(rng, r, n, p, dmin=1.0)
    try:
        peer = MarkerSpaceQP(J, d, lo, hi, max_iter=5000)
        q = MarkerSpaceQP(J, d / scale, lo, hi, max_iter=5000)
        trial = MarkerSpaceQP(J[:9], d / scale, lo, hi, max_iter=5000)
    except np.linalg.LinAlgError:
        return
    x = peer.solve(f, np.clip(np.zeros(n + p), lo, hi), 1)
    x = peer.solve(f + rng.normal(0, 1, n + p), x, 1)
    carry = peer._carry
    calls = []
    for qp in (q, trial):
        sub = qp._subproblem
        qp._subproblem = lambda fG, a, b, sub=sub, qp=qp: calls.append((qp, a.copy(), b.copy())) or sub(fG, a, b)
    g = f + rng.normal(0, 1, n + p)
    y = q.solve(g, x, 1, near=(peer, np.arange(r)))
    assert q.iterations == 1 or q._carry is None  # (None: settled into the primal method, to the optimum)
    assert np.array_equal(calls[0][1], carry[1]) and np.array_equal(calls[0][2], carry[2])
    trial.solve(g, x, 1, near=(peer, np.arange(9)))
    first = next(c for c in calls if c[0] is trial)
    xG = x[trial.G]
    assert np.array_equal(first[1], xG <= trial.lo) and np.array_equal(first[2], xG >= trial.hi)
    assert trial.iterations in (msq.FRESH_PASSES, 1) or trial._carry is None
    q._subproblem = q.__class__._subproblem.__get__(q)
    q.limits = (lo, hi)
    H = np.diag(d / scale) + J.T @ J
    np.testing.assert_allclose(_settle(q, H, g, y, 1), BoxQP(H, lo, hi).solve(g), atol=1e-7)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), r=st.integers(6, 30), n=st.integers(4, 70), p=st.integers(0, 3),
       scale=st.sampled_from([1e-3, 0.1, 1.0, 31.6, 100.0]), drop=st.floats(0.0, 0.5))
def test_s_from_a_peers_kept_s_is_the_fresh_one(seed, r, n, p, scale, drop):
    """A QP on some of a peer's rows with D scaled (kalman's held-out trial against the fit: a fold's markers out,
    another prior strength): its S for a free set, taken from the peer's kept S (block, scale, the pose projected
    off, the columns between the two free sets), is the S formed from its own columns; its solve from the peer's
    stop is the optimum (KKT, the dense solve)."""
    rng = np.random.default_rng(seed)
    J, d, lo, hi, f = _problem(rng, r, n, p, dmin=1.0)  # d / scale >= 1e-2
    rows = np.flatnonzero(rng.random(r) >= drop)
    try:
        peer = MarkerSpaceQP(J, d, lo, hi, max_iter=5000)
        q = MarkerSpaceQP(J[rows], d / scale, lo, hi, max_iter=5000)
    except np.linalg.LinAlgError:
        return
    assert q.ratio(peer) == pytest.approx(scale, rel=1e-12)
    x0 = peer.solve(f, np.clip(np.zeros(n + p), lo, hi), 1)
    if peer._L is None:
        return
    F = peer._F.copy()
    F[rng.random(n) < 0.2] ^= True
    q._near = (peer, rows)
    assert q._from_peer(F, n + 10)
    q._near = None
    W = q._Wt[F].T
    np.testing.assert_allclose(np.tril(q._S), np.tril(np.eye(len(rows)) + W @ W.T), rtol=0,
                               atol=1e-10 * (1 + np.abs(W).max() ** 2 * n))
    H = np.diag(d / scale) + J[rows].T @ J[rows]
    fresh, taken = (MarkerSpaceQP(J[rows], d / scale, lo, hi, max_iter=5000) for _ in range(2))
    x = taken.solve(f, x0, near=(peer, rows))
    assert x is not None
    _kkt(H, f, lo, hi, x, 1e-9)
    np.testing.assert_allclose(x, fresh.solve(f, x0), rtol=0, atol=1e-7)  # (rounding: 1.3e-9 seen at d / 100)
    np.testing.assert_allclose(x, BoxQP(H, lo, hi).solve(f), atol=1e-7)


def test_a_peer_at_a_disproportionate_d_or_other_limits_is_not_taken():
    rng = np.random.default_rng(2)
    J, d, lo, hi, _ = _problem(rng, 12, 40, 2, dmin=0.1)
    peer = MarkerSpaceQP(J, d, lo, hi)
    assert MarkerSpaceQP(J[:9], d * np.r_[np.full(20, 2.0), np.ones(22)], lo, hi).ratio(peer) is None  # a floor
    assert MarkerSpaceQP(J[:9], d, lo, hi + 1.0).ratio(peer) is None
    assert MarkerSpaceQP(J[:9], 3.0 * d, lo, hi).ratio(peer) == pytest.approx(1 / 3)


def test_a_trial_warm_from_the_fits_stop_takes_its_s_and_its_weights(monkeypatch):
    """kalman's pattern: a fit at one strength steps, a held-out trial at another strength on the frame's markers but
    a fold's is warmed from the fit's weights, begun and stepped: it takes the fit's kept S (no S over every free
    column) and returns the weights of a trial whose peers are forgotten (to rounding)."""
    import solvers.marker_space_qp as msq

    (B, lo, hi, mean, P), rng = _rig(8, 80)
    fit = FrameQP(B, lo, hi, prior=(mean, P), prior_weight=1e-2, frame_passes=1)
    trial, alone = (FrameQP(B, lo, hi, prior=(mean, P), prior_weight=1e-1, frame_passes=1) for _ in range(2))
    taken = []
    from_peer = msq.MarkerSpaceQP._from_peer
    monkeypatch.setattr(msq.MarkerSpaceQP, "_from_peer", lambda self, F, own: taken.append(
        from_peer(self, F, own)) or taken[-1])
    fold = np.ones(8, bool)
    fold[[1, 5]] = False
    begun = 0
    for s, seen in _moving_frames(B, rng, 40, 0.2):
        z = fit.step(s, seen)
        train = seen & fold
        if np.array_equal(train, seen):  # no held-out marker seen: no trial (HeldOutStrength)
            continue
        for qp in (trial, alone):
            qp.warm(z)
            if qp is alone:
                qp_module._STOPS.last = []
            begun += qp.begin(s, train, 1)
            w = qp.step(s, train)
        np.testing.assert_allclose(trial._prev, w, rtol=0, atol=1e-9)
    assert begun > 20 and any(taken)


def test_the_threads_record_of_stops_keeps_no_solver_alive():
    """A worker thread's record of its last marker-space stops does not keep a finished take's solvers (and their
    S and J) alive; a later solve on another basis takes no peer from it."""
    import gc
    import weakref

    (B, lo, hi, mean, P), rng = _rig(8, 80)
    fit = FrameQP(B, lo, hi, prior=(mean, P), prior_weight=1e-2, frame_passes=1)
    for s, seen in _moving_frames(B, rng, 10, 0.2):
        fit.step(s, seen)
    solvers = [weakref.ref(ws.marker_space) for ws in fit._models.values() if ws.marker_space]
    assert solvers and qp_module._STOPS.last
    del fit
    gc.collect()
    assert all(ref() is None for ref in solvers)
    (B2, lo, hi, mean, P), rng = _rig(8, 80, seed=1)
    other = FrameQP(B2, lo, hi, prior=(mean, P), prior_weight=1e-2, frame_passes=1)
    other.step(*next(_moving_frames(B2, rng, 1, 0.2)))
    assert all(other._near(ws) is None for ws in other._models.values() if ws.marker_space)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), r=st.integers(9, 24), n=st.integers(30, 60), p=st.integers(1, 3),
       hidden=st.integers(1, 3))
def test_a_pattern_with_rows_hidden_takes_its_s_from_the_whole_patterns(seed, r, n, p, hidden):
    """A pattern missing some rows (markers hidden) forms S with every column free from the all-rows QP's (the same
    d): its block, the pose's range projected off -- equal to the r x r x n product, and the solve's x the fresh
    solver's (issue 39: a new pattern's solver at 72 x 1000 ~4.2 -> ~2.7 ms)."""
    rng = np.random.default_rng(seed)
    J, d, lo, hi, f = _problem(rng, r, n, p)
    rows = np.sort(rng.choice(r, r - hidden, replace=False))
    whole = MarkerSpaceQP(J, d, lo, hi)
    try:
        fresh = MarkerSpaceQP(J[rows], d, lo, hi, max_iter=5000)
    except np.linalg.LinAlgError:  # too few rows left to fix the pose
        return
    taken = MarkerSpaceQP(J[rows], d, lo, hi, max_iter=5000, whole=(whole, rows))
    scale = 1 + np.abs(fresh._S_all).max()
    np.testing.assert_allclose(np.tril(taken._S_all), np.tril(fresh._S_all), rtol=0, atol=1e-11 * scale)
    x0 = np.clip(rng.normal(0, 1, n + p), lo, hi)
    x = taken.solve(f, x0)
    assert x is not None
    _kkt(np.diag(d) + J[rows].T @ J[rows], f, lo, hi, x, 1e-9)
    np.testing.assert_allclose(x, fresh.solve(f, x0), rtol=0, atol=1e-7)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), p=st.integers(0, 3), c=st.floats(0.1, 10.0))
def test_a_qp_at_another_strength_reads_the_same_js_arrays(seed, p, c):
    """``same``: a QP on the same J at another d (a prior strength) reads the peer's projected J and pose factor
    instead of forming copies (issue 39: one J in the caches for every strength's trial on a fold), and solves as a
    fresh one, bit for bit; another J is not taken."""
    rng = np.random.default_rng(seed)
    J, d, lo, hi, f = _problem(rng, 12, 40, p)
    first = MarkerSpaceQP(J, d, lo, hi)
    d2 = np.where(d > 0, c * d, 0.0)
    taken, fresh = MarkerSpaceQP(J.copy(), d2, lo, hi, same=first), MarkerSpaceQP(J, d2, lo, hi)
    assert taken.J is first.J
    x0 = np.clip(rng.normal(0, 1, 40 + p), lo, hi)
    np.testing.assert_array_equal(taken.solve(f, x0), fresh.solve(f, x0))
    other = MarkerSpaceQP(J + 1e-3, d2, lo, hi, same=first)
    assert other.J is not first.J


def test_frameqps_alike_share_each_patterns_j_and_step_as_alone():
    """FrameQPs built ``like`` one another (kalman's fits and trials at each strength) give each visibility pattern's
    marker-space solvers one projected J between them; the weights are those of a FrameQP built alone."""
    (B, lo, hi, mean, P), rng = _rig(8, 80)
    a = FrameQP(B, lo, hi, prior=(mean, P), prior_weight=1e-2)
    b = FrameQP(B, lo, hi, prior=(mean, P), prior_weight=1e-1, like=a)
    alone = FrameQP(B, lo, hi, prior=(mean, P), prior_weight=1e-1)
    for s, seen in _moving_frames(B, rng, 30, 0.2):
        a.step(s, seen)
        np.testing.assert_array_equal(b.step(s, seen), alone.step(s, seen))
    shared = [key for key, ws in b._models.items() if ws.marker_space and key in a._models
              and a._models[key].marker_space]
    assert shared
    assert all(b._models[key].marker_space.J is a._models[key].marker_space.J for key in shared)
