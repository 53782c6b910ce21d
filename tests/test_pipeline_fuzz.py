"""Hypothesis throws malformed packets at a running ``livecap run`` (its own process, real
ZeroMQ): it never dies, solves every good frame in between, and counts each bad packet under
the kind the decoder gives it."""

import json
import os
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zmq
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from livecap.calibration.profile import calibrate
from livecap.demo.face import demo_rig
from transport.wire import encode_markers, topic
from transport.zmq_source import ZmqSource

ROOT = Path(__file__).resolve().parents[1]
TOPIC = topic("markers", "actor")


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    d = tmp_path_factory.mktemp("fuzz")
    rig, layout = demo_rig(0)
    neutral = layout.marker_rig(rig).neutral
    profile = calibrate(rig, layout, neutral)
    profile.save(d / "profile.npz")
    ctx = zmq.Context()
    pub = ctx.socket(zmq.XPUB)
    pub.bind("tcp://127.0.0.1:*")
    addr = pub.getsockopt(zmq.LAST_ENDPOINT).decode()
    stats = d / "stats.json"
    with open(d / "stderr.txt", "w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "livecap", "run", "--zmq-in", addr, "--profile",
                                 str(d / "profile.npz"), "--stats-file", str(stats),
                                 "--no-skip-stale"],  # every good frame in a burst is solved
                                stdout=subprocess.DEVNULL, stderr=err, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert pub.poll(30000), "livecap run never subscribed"
    pub.recv()
    oracle = ZmqSource("inproc://oracle", profile.labels, bind=True, context=ctx)
    state = {"proc": proc, "pub": pub, "stats": stats, "oracle": oracle, "labels": profile.labels,
             "neutral": neutral, "frame": 0, "good": 0}
    yield state
    proc.send_signal(signal.SIGTERM)
    proc.wait(timeout=20)
    assert proc.returncode == 0
    oracle.close()
    pub.close(0)
    ctx.term()


def read_stats(s, want_in):
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        assert s["proc"].poll() is None, "the session died"
        s["proc"].send_signal(signal.SIGUSR1)
        time.sleep(0.03)
        try:
            st_ = json.loads(s["stats"].read_text())
        except (OSError, ValueError):
            continue
        if st_["frames_out"] >= want_in:  # frames_out moves last: the frame is fully done
            return st_
    raise AssertionError("the session stopped taking frames")


def good_packet(s, frame, labels=None, **over):
    labels = labels or s["labels"]
    pos = s["neutral"][: len(labels)] + 0.0
    return encode_markers(frame, frame / 120, pos, np.ones(len(labels), bool), labels)


@st.composite
def bad_packets(draw, s):
    f = s["frame"]
    kind = draw(st.sampled_from(["bytes", "mutate", "version", "nan", "dup", "unknown", "stale", "again"]))
    if kind == "bytes":
        return draw(st.binary(max_size=300))
    if kind == "mutate":
        b = bytearray(good_packet(s, f + 1))
        for _ in range(draw(st.integers(1, 5))):
            b[draw(st.integers(0, len(b) - 1))] = draw(st.integers(0, 255))
        return bytes(b[: draw(st.integers(0, len(b)))])
    if kind == "version":
        m = msgpack.unpackb(good_packet(s, f + 1))
        m["v"] = draw(st.integers(2, 1000))
        return msgpack.packb(m)
    if kind == "nan":
        pos = s["neutral"].copy()
        pos[draw(st.integers(0, len(pos) - 1)), draw(st.integers(0, 2))] = draw(st.sampled_from([np.nan, np.inf]))
        return encode_markers(f + 1, 0.0, pos, np.ones(len(pos), bool), s["labels"])
    if kind == "dup":
        labels = list(s["labels"])
        labels[1] = labels[0]
        return good_packet(s, f + 1, labels)
    if kind == "unknown":
        return good_packet(s, f + 1, [*s["labels"][:5], "not_a_marker"])
    if kind == "stale":
        return good_packet(s, max(0, f - draw(st.integers(1, 30))))  # within the reorder window
    return good_packet(s, f)  # "again": the last good frame repeated


@given(st.data())
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
def test_running_pipeline_survives_and_counts(session, data):
    s = session
    if s["frame"] == 0:  # a first good frame, so stale/duplicate have something to compare with
        s["frame"] = 1
        s["pub"].send_multipart([TOPIC, good_packet(s, 1)])
        s["oracle"].decode([TOPIC, good_packet(s, 1)])
        s["good"] += 1
    batch = data.draw(st.lists(bad_packets(s), min_size=1, max_size=8))
    before = Counter(s["oracle"].bad.counts)
    accepted = 0
    for payload in batch:
        s["pub"].send_multipart([TOPIC, payload])
        if s["oracle"].decode([TOPIC, payload]) is not None:
            accepted += 1  # a mutation that happens to be a valid, newer frame
    s["frame"] = max(s["frame"], s["oracle"]._order.last or 0) + 1
    s["pub"].send_multipart([TOPIC, good_packet(s, s["frame"])])
    assert s["oracle"].decode([TOPIC, good_packet(s, s["frame"])]) is not None
    s["good"] += 1 + accepted
    stats = read_stats(s, s["good"])
    assert stats["frames_in"] == stats["frames_out"] == s["good"], (batch, stats["bad_input"], s["oracle"].bad.counts)
    assert stats["bad_input"] == {k: v for k, v in s["oracle"].bad.counts.items() if v}
    assert sum(s["oracle"].bad.counts.values()) - sum(before.values()) == len(batch) - accepted

