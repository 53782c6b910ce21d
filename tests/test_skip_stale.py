"""Staying current when the solver is slower than the stream (Pipeline ``skip_stale``).

The logic is checked on a simulated clock (no wall-clock timing is asserted): frames arrive every
period P, the fake solver takes S per frame. Without skipping, latency grows with every frame
when S > P; with skipping, every solved frame was the newest one when its solve began, so its
latency is below min(P, S) + S (at most two solve times) however long the stream. A real
ZeroMQ burst checks ``ZmqSource.pending``.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import zmq
from hypothesis import given, settings
from hypothesis import strategies as st

from livecap.calibration.profile import calibrate
from livecap.core.take import MarkerFrame
from livecap.live.pipeline import Pipeline
from livecap.modes.registry import MODES
from transport.replay import ReplaySource
from transport.wire import encode_markers, topic
from transport.zmq_source import ZmqSource


@pytest.fixture(scope="module")
def profile(demo):
    rig, layout = demo
    return calibrate(rig, layout, layout.marker_rig(rig).neutral)


class Clock:
    now = 0.0


class SimulatedSource:
    """Frame i arrives at i * period on the simulated clock; waiting for it advances the clock."""

    def __init__(self, clock: Clock, neutral: np.ndarray, n: int, period: float) -> None:
        self.clock, self.neutral, self.n, self.period = clock, neutral, n, period
        self.i = -1

    def __iter__(self):
        for i in range(self.n):
            self.clock.now = max(self.clock.now, i * self.period)
            self.i = i
            yield MarkerFrame(i, i * self.period, self.neutral, np.ones(len(self.neutral), bool))

    def pending(self) -> bool:
        return self.i + 1 < self.n and (self.i + 1) * self.period <= self.clock.now


class SlowSolver:
    def __init__(self, clock: Clock, m: int, seconds: float) -> None:
        self.clock, self.m, self.seconds = clock, m, seconds

    def step(self, target, valid):
        self.clock.now += self.seconds
        return np.zeros(self.m)


class Published:
    def __init__(self, clock: Clock) -> None:
        self.clock, self.frames, self.latency = clock, [], []

    def publish(self, r) -> None:
        self.frames.append(r.frame)
        self.latency.append(self.clock.now - r.timestamp)

    def close(self) -> None:
        pass


def simulate(profile, solve_periods: float, skip: bool, n: int = 120, period: float = 1 / 120):
    clock = Clock()
    out = Published(clock)
    source = SimulatedSource(clock, np.asarray(profile.source_neutral), n, period)
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(MODES, "slow-test", lambda prof, opts: SlowSolver(clock, len(prof.names), solve_periods * period))
        stats = Pipeline(source, [out], profile=profile, mode="slow-test", skip_stale=skip).run()
    return stats, out


@given(solve_periods=st.floats(0.05, 8.0))
@settings(max_examples=30, deadline=None)
def test_latency_stays_below_two_solve_times(profile, solve_periods):
    period = 1 / 120
    stats, out = simulate(profile, solve_periods, skip=True, period=period)
    assert stats["frames_in"] == 120 and stats["frames_out"] + stats["stale"] == 120
    assert out.frames == sorted(out.frames) and out.frames[-1] == 119  # in order; the newest is never lost
    solve = solve_periods * period
    # a solved frame was the newest when its solve began, so it waited less than one period, and
    # less than the previous solve: below min(P, S) + S; the last frame has no successor, below 2 S
    assert max(out.latency[:-1]) <= min(period, solve) + solve + 1e-9
    assert out.latency[-1] <= 2 * solve + 1e-9
    if solve_periods <= 1.0:
        assert stats["stale"] == 0  # a solver that keeps up solves every frame
    elif (solve_periods - 1.0) * 120 > 2:  # behind by more than two periods over the 120 frames
        assert stats["stale"] > 0


def test_without_skipping_latency_grows_with_every_frame(profile):
    period = 1 / 120
    stats, out = simulate(profile, 3.0, skip=False, period=period)
    assert stats["frames_out"] == 120 and stats["stale"] == 0
    lat = np.array(out.latency)
    assert np.all(np.diff(lat) > 0) and lat[-1] > 119 * 2 * period  # unbounded: ~2 periods more per frame
    stats, out = simulate(profile, 3.0, skip=True, period=period)
    assert max(out.latency) <= 4 * period + 1e-9 and stats["stale"] > 60


def test_source_without_pending_solves_every_frame(profile, monkeypatch):
    clock = Clock()
    monkeypatch.setitem(MODES, "slow-test", lambda prof, opts: SlowSolver(clock, len(prof.names), 0.05))
    frames = [MarkerFrame(i, i / 120, np.asarray(profile.source_neutral), np.ones(len(profile.labels), bool))
              for i in range(30)]
    stats = Pipeline(iter(frames), [], profile=profile, mode="slow-test", skip_stale=True).run()
    assert stats["frames_out"] == 30 and stats["stale"] == 0


def _burst(profile, monkeypatch, skip: bool, n: int = 60) -> tuple[dict, list[int]]:
    """n frames published in one burst over real ZeroMQ before the (slow) pipeline starts reading."""
    ctx = zmq.Context()
    pub = ctx.socket(zmq.XPUB)
    pub.bind("tcp://127.0.0.1:*")
    source = ZmqSource(pub.getsockopt(zmq.LAST_ENDPOINT).decode(), profile.labels, idle_timeout=0.3, context=ctx)
    assert pub.poll(10000)
    pub.recv()  # the subscription arrived
    neutral = np.asarray(profile.source_neutral)
    for i in range(n):
        pub.send_multipart([topic("markers", "actor"),
                            encode_markers(i, i / 120, neutral, np.ones(len(neutral), bool), profile.labels)])
    deadline = time.monotonic() + 10
    while not source.pending() and time.monotonic() < deadline:
        time.sleep(0.01)

    class Sleepy:  # a genuinely slow solver: 2 ms per frame
        def step(self, target, valid):
            time.sleep(0.002)
            return np.zeros(len(profile.names))

    class Frames:
        frames: list[int] = []

        def publish(self, r):
            self.frames.append(r.frame)

        def close(self):
            pass

    sink = Frames()
    sink.frames = []
    monkeypatch.setitem(MODES, "sleepy-test", lambda prof, opts: Sleepy())
    stats = Pipeline(source, [sink], profile=profile, mode="sleepy-test", skip_stale=skip).run()
    pub.close(0)
    ctx.term()
    return stats, sink.frames


def test_zmq_burst_solves_the_newest_and_counts_the_rest(profile, monkeypatch):
    stats, frames = _burst(profile, monkeypatch, skip=True)
    assert stats["frames_in"] == 60 and stats["stale"] > 0
    assert stats["frames_out"] + stats["stale"] == 60 and frames[-1] == 59
    stats, frames = _burst(profile, monkeypatch, skip=False)
    assert stats["frames_out"] == 60 and stats["stale"] == 0 and frames == list(range(60))


def test_replay_pending_only_when_paced_and_behind(profile):
    from livecap.core.take import Take

    n = len(profile.labels)
    take = Take(profile.labels, np.repeat(np.asarray(profile.source_neutral)[None], 3, 0), np.ones((3, n), bool), 50.0)
    paced = ReplaySource(take, speed=1.0)
    assert not paced.pending()  # nothing read yet
    it = iter(paced)
    next(it)
    time.sleep(0.05)  # 2.5 periods: the next frame is due
    assert paced.pending()
    fast = ReplaySource(take, fast=True)
    it = iter(fast)
    next(it)
    time.sleep(0.05)
    assert not fast.pending()
    slow = ReplaySource(take, speed=0.001)  # a frame every 20 s: nothing is due right after the first
    it = iter(slow)
    next(it)
    assert not slow.pending()
