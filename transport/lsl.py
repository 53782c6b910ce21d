"""Lab Streaming Layer (pylsl, which ships liblsl): a marker inlet and a weights outlet.

Markers: one stream, 3 float channels per marker (x, y, z), one sample per frame; a missing
marker is NaN. Labels come from the stream's XML description when every channel has one of the
form ``<marker>_X``/``_Y``/``_Z`` (or ``.x``/``:x``, any case; the LSL mocap meta-data convention
and the Qualisys/Vicon/OptiTrack connectors use such names); otherwise the stream is unlabelled
and each sample is a cloud of points. Units from the channels' ``unit`` (mm/cm/m; default mm).

Weights: one stream, ``m`` weight channels then the head pose (qx qy qz qw tx ty tz), labelled in
its description, at the session rate.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterator

import numpy as np

from livecap.core.result import SolveResult
from livecap.core.take import MarkerFrame
from livecap.core.units import MM_PER_UNIT
from transport.badinput import BadInput, FrameOrder

MARKER_TYPE = "Mocap"
WEIGHTS_TYPE = "BlendshapeWeights"
_AXIS = re.compile(r"^(.+?)[_.:\s-]?([xyzXYZ])$")
POSE = ("head_qx", "head_qy", "head_qz", "head_qw", "head_tx", "head_ty", "head_tz")


# liblsl's discovery kept on this machine (the loopback rule of transport/security.py): queries go to
# 127.0.0.1 only and an outlet answers on 127.0.0.1:16571 only. liblsl 1.18 still binds an outlet's
# data port (16572 up) on every interface; ListenAddress governs discovery alone (docs/live.md).
LOOPBACK_CONFIG = "[ports]\nIPv6 = disable\n[multicast]\nResolveScope = machine\nListenAddress = 127.0.0.1\n"


def confine(interface: str | None) -> None:
    """Keep LSL discovery on loopback unless ``--interface`` is given; then liblsl's own
    configuration applies (lsl_api.cfg, or its site-wide multicast default: a socket bound to one
    unicast address would not hear multicast queries). Call before the first stream object:
    liblsl reads its configuration once per process."""
    if interface:
        return
    import pylsl

    pylsl.set_config_content(LOOPBACK_CONFIG)


class LslError(OSError):
    """No such stream, or a stream livecap cannot read as markers."""


def channel_labels(info) -> list[str]:
    """The ``label`` of every channel in a StreamInfo's description (empty strings when absent)."""
    out = []
    ch = info.desc().child("channels").child("channel")
    while not ch.empty():
        out.append(ch.child_value("label"))
        ch = ch.next_sibling("channel")
    return out


def _unit(info) -> str:
    ch = info.desc().child("channels").child("channel")
    unit = ch.child_value("unit").strip().lower() if not ch.empty() else ""
    return {"millimeters": "mm", "centimeters": "cm", "meters": "m"}.get(unit, unit) or "mm"


def marker_labels(channels: list[str], count: int) -> list[str] | None:
    """Marker names when the channels are labelled x, y, z per marker, else None (unlabelled)."""
    if len(channels) != count or count % 3:
        return None
    names = []
    for i in range(0, count, 3):
        parts = [_AXIS.match(c.strip()) for c in channels[i:i + 3]]
        if not all(parts) or [p.group(2).lower() for p in parts] != ["x", "y", "z"]:
            return None
        base = {p.group(1) for p in parts}
        if len(base) != 1:
            return None
        names.append(base.pop())
    return names if len(set(names)) == len(names) else None


class LslMarkerSource:
    """Frames from an LSL marker stream found by name.

    With ``labels`` (the session's order) and a labelled stream, frames come in that order
    (markers the stream lacks are missing). An unlabelled stream, or ``labels=None``, gives each
    sample as a cloud: all finite points, in the stream's (meaningless) order.
    """

    def __init__(self, name: str, labels: list[str] | None = None, resolve_timeout: float = 10.0,
                 idle_timeout: float | None = None, poll: float = 0.2) -> None:
        import pylsl

        found = pylsl.resolve_byprop("name", name, 1, resolve_timeout)
        if not found:
            raise LslError(f"LSL stream {name!r}: not found on the network within {resolve_timeout:g} s")
        self.inlet = pylsl.StreamInlet(found[0], max_buflen=10, recover=True)
        info = self.inlet.info(timeout=resolve_timeout)
        self.inlet.open_stream(timeout=resolve_timeout)  # samples buffer from now on, not from the first pull
        self.name = name
        self.channels = info.channel_count()
        if self.channels < 3 or self.channels % 3:
            raise LslError(f"LSL stream {name!r}: {self.channels} channels is not x, y, z per marker")
        self.stream_labels = marker_labels(channel_labels(info), self.channels)
        unit = _unit(info)
        if unit not in MM_PER_UNIT:
            raise LslError(f"LSL stream {name!r}: unknown channel unit {unit!r}")
        self.scale = MM_PER_UNIT[unit]
        self.rate = float(info.nominal_srate()) or None
        self.labelled = self.stream_labels is not None and labels is not None
        self.labels = list(labels) if self.labelled else None
        if self.labelled:
            where = {lab: i for i, lab in enumerate(self.stream_labels)}
            self._map = np.array([where.get(lab, -1) for lab in self.labels])
            if (self._map < 0).all():
                raise LslError(f"LSL stream {name!r}: none of the session's labels among its channels "
                               f"({', '.join(self.stream_labels[:5])}...)")
        self.bad = BadInput(f"lsl {name}")
        self._order = FrameOrder()
        self.idle_timeout = idle_timeout
        self.poll = poll
        self.received = 0
        self.last_decode_seconds = 0.0
        self._running = True

    def pending(self) -> bool:
        return self.inlet.samples_available() > 0

    def stop(self) -> None:
        self._running = False

    def close(self) -> None:
        self._running = False
        self.inlet.close_stream()

    def decode(self, sample, timestamp: float) -> MarkerFrame | None:
        """One sample to a frame, or None (counted) when it cannot be one."""
        values = np.asarray(sample, dtype=np.float64)
        if values.shape != (self.channels,):
            self.bad.skip("malformed", f"{values.size} values, expected {self.channels}")
            return None
        pts = values.reshape(-1, 3) * self.scale
        valid = np.isfinite(pts).all(1)
        if not valid.any():
            self.bad.skip("nonfinite", "no finite marker in the sample")
            return None
        frame = self.received - 1  # samples in order, none lost (LSL runs over TCP)
        if self.labelled:
            has = self._map >= 0
            pos = np.zeros((len(self.labels), 3))
            ok = np.zeros(len(self.labels), dtype=bool)
            pos[has] = pts[self._map[has]]
            ok[has] = valid[self._map[has]]
            pos[~ok] = 0.0
            return MarkerFrame(frame, timestamp, pos, ok)
        return MarkerFrame(frame, timestamp, np.where(valid[:, None], pts, 0.0), valid)

    def __iter__(self) -> Iterator[MarkerFrame]:
        last_good = time.monotonic()
        while self._running:
            sample, ts = self.inlet.pull_sample(timeout=self.poll)
            if sample is None:
                if self.idle_timeout and time.monotonic() - last_good > self.idle_timeout:
                    return
                continue
            t0 = time.perf_counter()
            self.received += 1
            frame = self.decode(sample, ts)
            self.last_decode_seconds = time.perf_counter() - t0
            if frame is not None:
                last_good = time.monotonic()
                yield frame


def marker_outlet(name: str, labels: list[str] | None, n_channels: int, rate: float, source_id: str = ""):
    """An outlet for markers in millimetres; ``labels=None`` describes no channel (unlabelled)."""
    import pylsl

    info = pylsl.StreamInfo(name, MARKER_TYPE, n_channels, rate, pylsl.cf_float32, source_id or f"livecap-{name}")
    chans = info.desc().append_child("channels")
    for i in range(n_channels):
        ch = chans.append_child("channel")
        if labels is not None:
            ch.append_child_value("label", f"{labels[i // 3]}_{'XYZ'[i % 3]}")
        ch.append_child_value("unit", "millimeters")
        ch.append_child_value("type", "Position" + "XYZ"[i % 3])
    return pylsl.StreamOutlet(info)


LINGER = 0.5  # s: liblsl has no flush; an outlet destroyed at once loses the samples still in its send queue


def release(outlet) -> None:
    """Let connected inlets drain the last samples before the outlet goes (a take's last frame was lost
    without this), then drop it."""
    if outlet is not None and outlet.have_consumers():
        time.sleep(LINGER)


class LslWeightSink:
    """Weights and head pose as one LSL stream (``publish``/``close``, like every sink)."""

    def __init__(self, name: str, names: list[str], rate: float) -> None:
        import pylsl

        self.names = list(names)
        info = pylsl.StreamInfo(name, WEIGHTS_TYPE, len(names) + len(POSE), rate, pylsl.cf_float32,
                                f"livecap-{name}")
        chans = info.desc().append_child("channels")
        for label in [*self.names, *POSE]:
            chans.append_child("channel").append_child_value("label", label)
        self.outlet = pylsl.StreamOutlet(info)
        self.sent = 0

    def publish(self, result: SolveResult) -> None:
        sample = np.concatenate([result.weights, result.head_rotation, result.head_translation]).astype(np.float32)
        self.outlet.push_sample(sample.tolist())
        self.sent += 1

    def stats(self) -> dict:
        return {"sent": self.sent}

    def close(self) -> None:
        self.outlet = release(self.outlet)


class LslMarkerSender:
    """``livecap send --lsl``: frames to a marker outlet; ``strip`` drops the channel labels and
    shuffles each frame's markers (a cloud, as an optical system's unlabelled stream)."""

    def __init__(self, name: str, labels: list[str], rate: float, strip: bool = False, seed: int = 0) -> None:
        self.n = len(labels)
        self.strip = strip
        self.rng = np.random.default_rng(seed)
        self.outlet = marker_outlet(name, None if strip else labels, 3 * self.n, rate)

    def wait_for_consumer(self, timeout: float) -> bool:
        return bool(self.outlet.wait_for_consumers(timeout))

    def send(self, positions: np.ndarray, valid: np.ndarray) -> None:
        pts = np.where(np.asarray(valid, bool)[:, None], np.asarray(positions, np.float64), np.nan)
        if self.strip:
            pts = pts[self.rng.permutation(self.n)]
        self.outlet.push_sample(pts.astype(np.float32).ravel().tolist())

    def close(self) -> None:
        self.outlet = release(self.outlet)
