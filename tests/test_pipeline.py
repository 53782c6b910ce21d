"""The Pipeline in one process: same weights as the offline solve, calibration from the stream,
bad input and broken parts counted while the session keeps running, session files."""

import threading

import numpy as np
import pytest
import zmq
from hypothesis import given, settings
from hypothesis import strategies as st

from livecap.calibration.profile import calibrate, estimate_neutral
from livecap.demo.performance import PerformanceSettings, perform
from livecap.live.pipeline import Pipeline, StageTiming
from livecap.live.session import SessionError, load_session
from livecap.modes.registry import build_solver
from livecap.offline.solve import solve_take
from tests.sinks import Capture
from transport.recorders import JsonlRecorder, read_jsonl_recording
from transport.wire import encode_markers, topic
from transport.zmq_source import ZmqSource


@pytest.fixture(scope="module")
def setup(demo):
    rig, layout = demo
    perf = perform(rig, layout, PerformanceSettings(seconds=1.0, rate=120, seed=5))
    take = perf.take.select(layout.labels)
    profile = calibrate(rig, layout, estimate_neutral(take, layout.stable, 60))
    return rig, layout, take, profile


def test_pipeline_matches_offline_solve(setup):
    _, _, take, profile = setup
    cap = Capture()
    stats = Pipeline(take.frames(), [cap], profile=profile).run()
    offline = solve_take(take, profile, build_solver("lsq", profile), max_gap_seconds=0, pose_smoothing_seconds=0)
    assert stats["frames_in"] == stats["frames_out"] == take.n_frames == len(cap.results)
    W = np.stack([r.weights for r in cap.results])
    np.testing.assert_allclose(W, offline.weights, atol=1e-9)
    np.testing.assert_allclose(np.stack([r.head_rotation for r in cap.results]) *
                               np.sign(offline.head_rotation[:, 3:] * np.stack([r.head_rotation for r in cap.results])
                                       [:, 3:]), offline.head_rotation, atol=1e-9)
    assert cap.results[0].names == profile.names and cap.results[5].frame == take.first_frame + 5
    assert all(r.residual >= 0 and r.solve_time > 0 for r in cap.results)
    for stage in ("receive", "solve", "publish"):
        assert np.isfinite(stats["timing"][stage]["p99_ms"])


@pytest.mark.parametrize("mode", ["kalman", "robust-lag", "robust"])
def test_a_lagged_mode_publishes_each_frame_with_its_own_pose_and_markers(setup, mode):
    """kalman (1 frame) and robust-lag streamed (4) return frame t - L's weights at frame t: the pipeline
    pairs them with frame t - L's number, time, head pose and markers, and skips the first L outputs.
    The weights equal a fresh solver's: the warm-up step before the stream is undone by ``reset``."""
    _, _, take, profile = setup
    cap = Capture()
    stats = Pipeline(take.frames(), [cap], profile=profile, mode=mode).run()
    solver = build_solver(mode, profile)
    lag = int(solver.latency_frames)
    assert lag == {"kalman": 1, "robust-lag": 4, "robust": 0}[mode] and stats["mode"] == mode
    # at the end the last `lag` frames are drained (steps on frames with no marker seen): every frame comes out
    assert stats["frames_out"] == take.n_frames == len(cap.results)
    assert [r.frame for r in cap.results] == list(range(take.first_frame, take.first_frame + take.n_frames))
    offline = solve_take(take, profile, build_solver("lsq", profile), max_gap_seconds=0, pose_smoothing_seconds=0)
    q = np.stack([r.head_rotation for r in cap.results])
    np.testing.assert_allclose(np.abs(np.einsum("ti,ti->t", q, offline.head_rotation[:len(q)])), 1.0, atol=1e-9)
    fed = list(zip(*_targets(take, profile), strict=True))
    stepped = np.stack([solver.step(*f) for f in fed + _pads(fed[-1], lag)])[lag:]
    np.testing.assert_allclose(np.stack([r.weights for r in cap.results]), stepped, atol=1e-9)


def test_auto_resolves_with_the_profile_and_the_report_says_to_what(setup):
    _, _, take, profile = setup
    p = Pipeline(take.frames(), [Capture()], profile=profile, mode="auto", max_frames=5)
    assert p.run()["mode"] == "robust" and "mode robust" in p.report().splitlines()[0]


def test_a_solver_error_leaves_the_lagged_pairing_intact(setup):
    """A frame whose step raised was never seen by the solver: it must not enter the queue that pairs the
    lagged weights with their frames (robust-lag, 4 frames; the 11th step raises)."""
    _, _, take, profile = setup
    cap = Capture()
    p = Pipeline(take.frames(), [cap], profile=profile, mode="robust-lag")
    real, calls = p._solver.step, [0]

    def flaky(target, valid):
        calls[0] += 1
        if calls[0] == 11:
            raise FloatingPointError("boom")
        return real(target, valid)

    p._solver.step = flaky
    stats = p.run()
    assert stats["errors"]["solver_error"] == 1
    skipped = take.first_frame + 10
    solver = build_solver("robust-lag", profile)
    fed = [(t, v) for i, (t, v) in enumerate(zip(*_targets(take, profile), strict=True)) if i != 10]
    stepped = np.stack([solver.step(t, v) for t, v in fed + _pads(fed[-1], 4)])[4:]
    frames = [f for f in range(take.first_frame, take.first_frame + take.n_frames) if f != skipped]
    assert [r.frame for r in cap.results] == frames
    np.testing.assert_allclose(np.stack([r.weights for r in cap.results]), stepped, atol=1e-9)


def _pads(last, n):
    """What the pipeline steps on to drain a lagged solver: no marker seen."""
    target, valid = last
    return [(np.zeros_like(target), np.zeros(len(valid), bool))] * n


def _targets(take, profile):
    stab = profile.stabiliser()
    out = []
    for i in range(take.n_frames):
        local, _, _ = stab.step(take.positions[i], take.valid[i])
        out.append(np.where(take.valid[i][:, None], local - profile.source_neutral, 0.0))
    return out, list(take.valid)


def test_calibrates_on_the_stream_then_solves_every_frame(setup):
    rig, layout, take, _ = setup
    cap = Capture()

    def calibrator(t):
        return calibrate(rig, layout, estimate_neutral(t, layout.stable))

    p = Pipeline(take.frames(), [cap], calibrator=calibrator, calibrate_frames=30, labels=layout.labels)
    stats = p.run()
    assert stats["frames_out"] == take.n_frames
    assert [r.frame for r in cap.results] == list(range(take.first_frame, take.first_frame + take.n_frames))


def test_bad_input_is_counted_and_the_session_keeps_running(setup):
    _, layout, take, profile = setup
    ctx = zmq.Context()
    pub = ctx.socket(zmq.XPUB)
    pub.bind("tcp://127.0.0.1:*")
    src = ZmqSource(pub.getsockopt(zmq.LAST_ENDPOINT).decode(), profile.labels, context=ctx, idle_timeout=0.3)
    assert pub.poll(5000) and pub.recv() == b"\x01markers.actor"  # the source has subscribed
    tp = topic("markers", "actor")
    labels = profile.labels
    good = [encode_markers(f.frame, f.timestamp, f.positions, f.valid, labels) for f in take.slice(0, 10).frames()]
    sent = [good[0], b"junk", good[1], good[1], good[0], encode_markers(99, 0, np.zeros((1, 3)), [True], ["zz"]),
            good[2][:20], good[3]]
    for payload in sent:
        pub.send_multipart([tp, payload])
    pub.send_multipart([b"only-one-part"])
    cap = Capture()
    stats = Pipeline(src, [cap], profile=profile).run()
    assert [r.frame for r in cap.results] == [0, 1, 3]
    assert stats["bad_input"] == {"malformed": 1, "duplicate_frame": 1, "out_of_order": 1, "unknown_label": 1,
                                  "short": 1}
    pub.close(0)
    ctx.term()


def test_broken_sink_and_solver_errors_are_counted(setup):
    _, _, take, profile = setup

    class Broken:
        def publish(self, r):
            raise RuntimeError("disk on fire")

        def close(self):
            pass

    cap = Capture()
    p = Pipeline(take.slice(0, 5).frames(), [Broken(), cap], profile=profile)
    calls = []
    real = p._solver.step

    def flaky(target, valid):
        calls.append(1)
        if len(calls) == 2:
            raise FloatingPointError("boom")
        return real(target, valid)

    p._solver.step = flaky
    stats = p.run()
    assert len(cap.results) == 4 and stats["errors"] == {"sink_error": 4, "solver_error": 1}


def test_stop_from_another_thread_flushes_recorders(setup, tmp_path):
    _, _, take, profile = setup
    from transport.replay import ReplaySource

    rec = JsonlRecorder(tmp_path / "w.jsonl")
    p = Pipeline(ReplaySource(take, profile.labels, loop=True), [rec], profile=profile, flush_every=100)
    threading.Timer(0.4, p.stop).start()
    stats = p.run()
    names, frames = read_jsonl_recording(tmp_path / "w.jsonl")
    assert stats["frames_out"] > 0 and len(frames) == stats["frames_out"] and names == profile.names


def test_stage_timing_percentiles():
    t = StageTiming(window=100)
    for x in range(1000):
        t.add(x / 1000)
    p = t.percentiles()
    assert p["max_ms"] == 999 and 940 < p["p50_ms"] < 960 and p["p99_ms"] > 995


def test_session_file(tmp_path):
    f = tmp_path / "s.toml"
    f.write_text('mode = "lsq"\nprofile = "p.npz"\n[source]\nzmq-in = "tcp://127.0.0.1:5"\n'
                 '[sinks]\nrecord_csv = "out/w.csv"\n[options]\nridge = 0.5\n')
    known = {"mode", "profile", "zmq_in", "record_csv"}
    settings, options = load_session(f, known)
    assert settings["zmq_in"] == "tcp://127.0.0.1:5" and options == {"ridge": 0.5}
    assert settings["profile"] == str(tmp_path / "p.npz") and settings["record_csv"] == str(tmp_path / "out/w.csv")
    f.write_text('[sinks]\nvmcc = "1"\n')
    with pytest.raises(SessionError, match=r"s.toml: unknown setting \[sinks\] 'vmcc'"):
        load_session(f, known)
    f.write_text("mode = \n")
    with pytest.raises(SessionError, match="not valid TOML"):
        load_session(f, known)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 40), st.integers(1, 60), st.floats(0.0, 1.0))
def test_compiled_fit_quality_equals_numpy(seed, n, m, seen):
    """The pipeline's RMS residual and at-bound flags (compiled) equal the numpy expressions they replaced."""
    from solvers.residual_kernels import fit_quality

    rng = np.random.default_rng(seed)
    basis = rng.normal(0, 3, (3 * n, m))
    w = rng.uniform(-0.2, 1.2, m)
    w[rng.random(m) < 0.2] = 1.0  # exactly at a bound
    target = rng.normal(0, 2, (n, 3))
    valid = rng.random(n) < seen
    lower, upper = np.zeros(m), np.ones(m)
    rms, at_bound = fit_quality(basis, w, target, valid, lower, upper)
    miss = (basis @ w).reshape(-1, 3) - target
    want = float(np.sqrt(np.einsum("ij,ij->i", miss, miss)[valid].mean() / 3.0)) if valid.any() else 0.0
    assert rms == pytest.approx(want, rel=1e-12, abs=1e-12)
    assert at_bound.dtype == np.int8
    np.testing.assert_array_equal(at_bound, (w >= upper).astype(np.int8) - (w <= lower))
