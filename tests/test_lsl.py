"""Lab Streaming Layer: a real pylsl outlet in another process (labelled, then unlabelled and
shuffled by ``livecap send --lsl --strip-labels``) feeding the inlet and ``livecap run --lsl-in``;
weights read back through a real inlet."""

import os
import subprocess
import sys
import textwrap
import uuid
from pathlib import Path

import numpy as np
import pytest

from transport.lsl import LslError, LslMarkerSource, marker_labels
from transport.recorders import read_jsonl_recording

pylsl = pytest.importorskip("pylsl")
ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}

OUTLET = """
import sys, time, numpy as np, pylsl
name, labelled, n_frames = sys.argv[1], sys.argv[2] == "1", int(sys.argv[3])
labels = ["A", "B", "C"]
info = pylsl.StreamInfo(name, "Mocap", 9, 120, pylsl.cf_float32, name)
chans = info.desc().append_child("channels")
for lab in labels:
    for ax in "XYZ":
        ch = chans.append_child("channel")
        if labelled:
            ch.append_child_value("label", f"{lab}_{ax}")
        ch.append_child_value("unit", "centimeters")
out = pylsl.StreamOutlet(info)
print("ready", flush=True)
out.wait_for_consumers(20)
time.sleep(0.3)
for f in range(n_frames):
    s = [f + 0.1 * i for i in range(9)]
    if f == 3:
        s = [float("nan")] * 9  # nothing visible: counted and skipped
    if f == 4:
        s[3:6] = [float("nan")] * 3  # B missing
    out.push_sample(s)
    time.sleep(1 / 240)
time.sleep(1.0)
"""


def test_marker_labels_from_channels():
    assert marker_labels(["a_X", "a_Y", "a_Z", "b.x", "b.y", "b.z"], 6) == ["a", "b"]
    assert marker_labels(["a_X", "a_Y", "a_Z", "", "", ""], 6) is None
    assert marker_labels(["a_X", "a_Z", "a_Y"], 3) is None
    assert marker_labels(["a_X", "a_Y", "a_Z", "a_X", "a_Y", "a_Z"], 6) is None


def _outlet(tmp_path, labelled, n):
    name = f"livecap-test-{uuid.uuid4().hex[:8]}"
    script = tmp_path / "outlet.py"
    script.write_text(textwrap.dedent(OUTLET))
    proc = subprocess.Popen([sys.executable, str(script), name, "1" if labelled else "0", str(n)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready", proc.stderr.read()
    return name, proc


@pytest.mark.parametrize("labelled", [True, False])
def test_inlet_reads_a_real_outlet(tmp_path, labelled):
    name, proc = _outlet(tmp_path, labelled, 10)
    try:
        src = LslMarkerSource(name, ["C", "A", "Z"], idle_timeout=0.8)
        assert src.labelled is labelled and src.rate == 120
        frames = list(src)
    finally:
        proc.wait(timeout=20)
    assert [f.frame for f in frames] == [0, 1, 2, 4, 5, 6, 7, 8, 9]
    assert src.bad.as_dict() == {"nonfinite": 1}
    f5 = frames[4]
    if labelled:  # session order, centimetres -> mm, a label the stream lacks is missing
        np.testing.assert_allclose(f5.positions[:2], 10 * np.array([[5.6, 5.7, 5.8], [5.0, 5.1, 5.2]]), rtol=1e-6)
        assert f5.valid.tolist() == [True, True, False]
        assert frames[3].valid.tolist() == [True, True, False]
    else:  # the cloud as sent
        assert f5.positions.shape == (3, 3) and f5.valid.all()
        assert frames[3].valid.tolist() == [True, False, True]


def test_unknown_stream_is_one_clear_error():
    with pytest.raises(LslError, match="not found"):
        LslMarkerSource(f"livecap-absent-{uuid.uuid4().hex[:6]}", resolve_timeout=0.5)


def _livecap(*args):
    return subprocess.Popen([sys.executable, "-m", "livecap", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=ENV)


def test_run_lsl_unlabelled_against_send_strip_labels(tmp_path):
    """``livecap send TAKE --lsl NAME --strip-labels`` -> ``livecap run --lsl-in NAME --unlabelled``:
    the weights of the labelled replay of the same frames, and an LSL weights outlet read back."""
    from livecap.calibration.profile import calibrate, estimate_neutral
    from livecap.demo.face import demo_rig
    from transport.takefile import read_take

    take_path = ROOT / "recordings" / "demo_take.c3d"
    rig, layout = demo_rig(0)
    take = read_take(take_path).select(layout.labels)
    profile = calibrate(rig, layout, estimate_neutral(take, layout.stable, 120))
    profile.save(tmp_path / "p.npz")
    n = 360
    name, wname = f"livecap-m-{uuid.uuid4().hex[:8]}", f"livecap-w-{uuid.uuid4().hex[:8]}"
    send = _livecap("send", take_path, "--lsl", name, "--strip-labels", "--end", n, "--wait-subscriber", 30)
    assert send.stdout.readline().startswith("ready: lsl"), send.stderr.read()
    run = _livecap("run", "--lsl-in", name, "--unlabelled", "--profile", tmp_path / "p.npz", "--zmq-out",
                   "tcp://127.0.0.1:*", "--lsl-out", wname, "--record-jsonl", tmp_path / "live.jsonl",
                   "--no-skip-stale", "--idle-timeout", "1.5")
    ready = run.stdout.readline()
    assert "lsl-in" in ready and "(unlabelled)" in ready and "zmq-out" in ready, run.stderr.read()
    weights_in = pylsl.StreamInlet(pylsl.resolve_byprop("name", wname, 1, 10)[0])
    got = []
    while True:
        sample, _ = weights_in.pull_sample(timeout=3.0)
        if sample is None:
            break
        got.append(sample)
    assert send.wait(60) == 0 and run.wait(60) == 0, run.stderr.read()
    report = run.stdout.read()
    assert f"frames in {n}, out {n}" in report, report
    replay = _livecap("run", "--replay", take_path, "--end", n, "--fast", "--profile", tmp_path / "p.npz",
                      "--record-jsonl", tmp_path / "labelled.jsonl")
    assert replay.wait(120) == 0, replay.stderr.read()
    _, live = read_jsonl_recording(tmp_path / "live.jsonl")
    _, ref = read_jsonl_recording(tmp_path / "labelled.jsonl")
    W, R = np.array([r["weights"] for r in live]), np.array([r["weights"] for r in ref])
    assert W.shape == R.shape == (n, len(profile.names))
    # live, a marker coming back after a gap is withheld one frame (docs/capture.md): close, not equal
    rms = np.sqrt(np.mean((W - R) ** 2))
    assert rms < 0.003 and np.abs(W - R).max() < 0.05 and np.ptp(W, axis=0).max() > 0.2, rms
    assert len(got) == n and len(got[0]) == len(profile.names) + 7
    np.testing.assert_allclose(np.array(got)[:, :len(profile.names)], W, atol=1e-5)
