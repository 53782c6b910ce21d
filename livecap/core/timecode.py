"""Time-of-day timecode for the frames a session publishes, so its streams line up with other
timecoded sources (the Live Link Face app stamps its packets and CSV rows with the phone's time of
day, SMPTE-style ``HH:MM:SS:FF``).

A :class:`TimecodeClock` maps the stream's own timestamps to a time of day, so frames stay evenly
spaced whatever the solve's jitter:

* ``"clock"`` (default): the system clock's local time of day at capture. Each frame is anchored
  at the time it reached livecap (``received``, stamped by the pipeline as the source hands it
  over), not at the time it is published, so frames held back while the session calibrates on the
  stream, or published late after a stall, keep their capture spacing (issue 37.2: anchored at
  publication, the calibration burst was stamped at half the frame step). The offset between
  timestamps and arrival follows the smallest seen (the least-delayed frame is the closest to its
  capture) and comes down by at most half of each frame step (``SLEW``), so network jitter never
  makes the timecode repeat or run backwards. A result with no arrival time falls back to the
  clock at publication.
* ``"HH:MM:SS:FF"``: that start timecode for the first frame (frames at the stream's rate);
* ``"take"``: the take's own timestamps as the time of day.
"""

from __future__ import annotations

import datetime as _dt
import math
import re
from dataclasses import dataclass, field

SECONDS_PER_DAY = 86400.0
SLEW = 0.5  # the clock offset comes down by at most this fraction of each frame step
_TC = re.compile(r"^(\d{1,2}):(\d{2}):(\d{2})[:;](\d{1,3})$")


def frame_rate_fraction(rate: float) -> tuple[int, int]:
    """Frame rate as numerator / denominator: NTSC rates (29.97, 59.94, 23.976, 119.88) are
    ``n*1000/1001``, whole rates ``n/1``."""
    if rate <= 0 or not math.isfinite(rate):
        raise ValueError(f"frame rate must be positive, got {rate}")
    if abs(rate - round(rate)) < 1e-3:
        return int(round(rate)), 1
    ntsc = round(rate * 1.001)
    if abs(ntsc * 1000 / 1001 - rate) < 5e-3:
        return ntsc * 1000, 1001
    return int(round(rate * 1000)), 1000


def parse_timecode(text: str, rate: float) -> float:
    """Seconds of day of ``HH:MM:SS:FF`` at ``rate`` frames per second."""
    m = _TC.match(text.strip())
    if not m:
        raise ValueError(f"--timecode {text!r}: expected HH:MM:SS:FF, 'clock' or 'take'")
    h, mi, s, f = (int(g) for g in m.groups())
    nominal = max(1, int(round(rate)))
    if h > 23 or mi > 59 or s > 59 or f >= nominal:
        raise ValueError(f"--timecode {text!r}: out of range (frames 0-{nominal - 1} at {rate:g} fps)")
    return h * 3600 + mi * 60 + s + f / nominal


def now_of_day(epoch: float | None = None) -> float:
    """The system clock's local time of day, seconds (now, or at ``epoch``, seconds since 1970 as time.time())."""
    now = _dt.datetime.now() if epoch is None else _dt.datetime.fromtimestamp(epoch)
    return now.hour * 3600 + now.minute * 60 + now.second + now.microsecond * 1e-6


@dataclass
class TimecodeClock:
    """Time of day (seconds) of each published frame; see the module doc for ``start``."""

    start: str = "clock"
    rate: float = 60.0
    _offset: float | None = field(default=None, init=False)
    _last: float | None = field(default=None, init=False)

    def __post_init__(self) -> None:
        if self.start not in ("clock", "take"):
            parse_timecode(self.start, self.rate)  # a bad start fails before the session runs

    def seconds_of_day(self, timestamp: float, received: float | None = None) -> float:
        """Time of day of the frame at ``timestamp`` (stream seconds) that reached livecap at ``received``
        (wall clock, time.time(); ``None``: now)."""
        ts = float(timestamp)
        if self.start == "take":
            return ts % SECONDS_PER_DAY
        if self.start == "clock":
            offset = (now_of_day() if received is None else now_of_day(received)) - ts
            if self._offset is None:
                self._offset = offset
            elif offset < self._offset and self._last is not None and ts > self._last:
                self._offset = max(offset, self._offset - SLEW * (ts - self._last))
            self._last = ts if self._last is None else max(self._last, ts)
        elif self._offset is None:
            self._offset = parse_timecode(self.start, self.rate) - ts
        return (self._offset + ts) % SECONDS_PER_DAY


def split_frames(seconds_of_day: float, fps: float) -> tuple[int, float]:
    """Whole frames since midnight at ``fps`` and the sub-frame fraction in [0, 1)."""
    total = seconds_of_day * fps
    whole = math.floor(total + 1e-6)
    return int(whole), min(max(total - whole, 0.0), 0.999999)


def format_timecode(seconds_of_day: float, fps: int = 60, sub_digits: int = 3) -> str:
    """``HH:MM:SS:FF.mmm``: frames FF at ``fps`` (00 to fps-1), then the sub-frame in thousandths
    (the Live Link Face app's CSV timecode, written at 60 fps)."""
    whole, sub = split_frames(seconds_of_day, fps)
    scale = 10**sub_digits
    sub_i = min(int(sub * scale), scale - 1)
    s, ff = divmod(whole, fps)
    return f"{s // 3600 % 24:02d}:{s // 60 % 60:02d}:{s % 60:02d}:{ff:02d}.{sub_i:0{sub_digits}d}"
