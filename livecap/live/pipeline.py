"""The live pipeline: source -> stabilise -> solver -> sinks, one frame at a time.

Per frame: remove head motion against the actor's neutral (Seol et al. 2012 §3.1), hand the
stabilised displacement to the chosen solver mode's ``step``, wrap the weights and head pose in
a :class:`~livecap.core.result.SolveResult` and give it to every sink. Nothing in the loop waits on
a consumer: sinks send without blocking (transport/), recorders write to the OS and are
flushed every ``flush_every`` seconds.

With no profile, the first ``calibrate_frames`` frames of the stream are the neutral face
(Curio et al. 2006 §2.1): the pipeline calibrates on them, then solves and publishes them
(late, in order) before carrying on live.

Staying current (``skip_stale``): when the solver is slower than the stream, frames would
queue in the source and the latency would grow without bound. With ``skip_stale`` the loop asks
the source whether another frame is already waiting (``source.pending()``); if so, the frame in
hand is counted as *stale* and not solved, so only the newest waiting frame is solved and
latency stays within about two solve times. Every frame is still recorded by the marker
recorder. On by default for live network sources in ``livecap run``; off for file replay,
where every frame must be solved.

Timing is kept per stage (receive = decoding the packet, solve = stabilise + solver step,
step = the mode's ``step`` alone, publish = all sinks and recorders; frame = everything the driver
does for a solved frame, decoding to the last sink; around_step = frame less the mode's step, the
driver's own cost per frame, issue 18) as running p50/p99 over the last few thousand frames;
:meth:`report` formats them, on exit, on SIGUSR1, or periodically.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from livecap.calibration.profile import CalibrationError, Profile
from livecap.calibration.stabilise import to_quaternion
from livecap.core.result import BOUND_TOL, SolveResult
from livecap.core.take import MarkerFrame, Take
from livecap.modes.registry import build_solver, resolve_mode

log = logging.getLogger("livecap.live.pipeline")

STAGES = ("receive", "solve", "step", "publish", "frame", "around_step")


class StageTiming:
    """A ring of the last ``window`` durations of one stage; percentiles on request. A list, not an array:
    :meth:`add` runs per frame, and a numpy store on a process just woken by a packet costs ~10-30 us
    (docs/iphone.md, Latency)."""

    def __init__(self, window: int = 4096) -> None:
        self.samples = [0.0] * window
        self.count = 0

    def add(self, seconds: float) -> None:
        self.samples[self.count % len(self.samples)] = seconds
        self.count += 1

    def percentiles(self) -> dict[str, float]:
        k = min(self.count, len(self.samples))
        if k == 0:
            return {"p50_ms": float("nan"), "p99_ms": float("nan"), "max_ms": float("nan")}
        s = np.array(self.samples[:k]) * 1e3
        p50, p99 = np.percentile(s, [50, 99])
        return {"p50_ms": float(p50), "p99_ms": float(p99), "max_ms": float(s.max())}


def solver_latency(solver: object) -> int:
    """Frames between a solver's input and the frame its ``step`` output belongs to (0 when it says none)."""
    lag = getattr(solver, "latency_frames", getattr(solver, "lookahead", 0))
    return int(lag) if isinstance(lag, int | np.integer) else 0


class Pipeline:
    def __init__(self, source: Iterable[MarkerFrame], sinks: list, *, profile: Profile | None = None,
                 calibrator: Callable[[Take], Profile] | None = None, calibrate_frames: int = 120,
                 labels: list[str] | None = None, rate: float = 120.0, mode: str = "lsq",
                 options: dict | None = None, marker_recorder=None, flush_every: float = 0.1,
                 max_frames: int | None = None, stats_file: str | Path | None = None,
                 stats_every: float | None = None, skip_stale: bool = False) -> None:
        if profile is None and calibrator is None:
            raise ValueError("the pipeline needs a profile or a way to calibrate from the stream")
        self.source = source
        self.sinks = list(sinks)
        self.profile = profile
        self.calibrator = calibrator
        self.calibrate_frames = max(1, int(calibrate_frames))
        self.labels = list(profile.labels if profile is not None else labels or [])
        self.rate = rate
        self.mode = mode
        self.options = dict(options or {})
        self.marker_recorder = marker_recorder
        self.flush_every = flush_every
        self.max_frames = max_frames
        self.stats_file = Path(stats_file) if stats_file else None
        self.stats_every = stats_every
        self.timing = {s: StageTiming() for s in STAGES}
        self.frames_in = 0
        self.frames_out = 0
        self.stale = 0
        self.skip_stale = bool(skip_stale)
        self._pending = getattr(source, "pending", None) if skip_stale else None
        self._stale_logged = (-1e9, 0)
        self.errors: Counter[str] = Counter()
        self._error_log: dict[str, float] = {}
        self._stop = threading.Event()
        self._buffer: list[MarkerFrame] = []
        self._solver = None
        self.solver_mode: str | None = None  # the mode ``mode`` resolved to with the profile (auto: kalman or robust)
        self._step_time = 0.0
        self._started = 0.0
        self._cpu0 = 0.0
        if profile is not None:
            self._prepare(profile)

    # ------------------------------------------------------------------ setup
    def _prepare(self, profile: Profile) -> None:
        self.profile = profile
        self.labels = list(profile.labels)
        self._names = list(profile.names)
        self._stabiliser = profile.stabiliser()
        self._neutral = np.asarray(profile.source_neutral, dtype=float)
        self._basis = np.ascontiguousarray(profile.basis, dtype=float)
        self._bounds = (np.asarray(profile.lower, dtype=float) + BOUND_TOL, np.asarray(profile.upper, dtype=float)
                        - BOUND_TOL)
        from solvers.residual_kernels import fit_quality  # numba loads with a profile, not with `livecap --help`

        self._fit_quality = fit_quality
        self.solver_mode = resolve_mode(self.mode, profile, self.options)
        self._solver = build_solver(self.solver_mode, profile, self.options)
        self._lagged: deque = deque(maxlen=solver_latency(self._solver) + 1)
        self._warm_up()

    def _warm_up(self) -> None:
        """The head fit and, when it can ``reset``, the solver step once on the neutral face, then forget it: their
        compiled kernels load (or, after an install, compile: seconds) here rather than on the stream's first frame."""
        n = len(self.labels)
        t0 = time.perf_counter()
        try:
            jumped = self._neutral.copy()  # one stable marker off by 50 mm: the refit's kernel loads too
            jumped[np.flatnonzero(self._stabiliser.stable)[:1]] += 50.0
            for pose in (self._neutral, jumped):
                self._stabiliser.step(pose, np.ones(n, bool))
            self._stabiliser.reset()
            self._fit_quality(self._basis, np.zeros(self._basis.shape[1]), np.zeros((n, 3)), np.ones(n, bool),
                              *self._bounds)
            if hasattr(self._solver, "reset"):
                self._solver.step(np.zeros((n, 3)), np.ones(n, bool))
                self._solver.reset()
        except Exception as exc:  # a solver that cannot step a neutral frame still gets the stream
            log.warning("warm-up failed (%s: %s)", type(exc).__name__, exc)
        log.debug("warm-up %.3f s", time.perf_counter() - t0)

    def _calibrate(self) -> bool:
        frames = self._buffer
        take = Take(self.labels, np.stack([f.positions for f in frames]), np.stack([f.valid for f in frames]),
                    self.rate, frames[0].frame)
        try:
            profile = self.calibrator(take)
        except CalibrationError as exc:
            self._error("calibration", f"{exc}; collecting more frames")
            self.calibrate_frames += max(1, len(frames) // 2)
            return False
        self._prepare(profile)
        log.info("calibrated on %d frames from the stream (frames %d..%d)", len(frames), frames[0].frame,
                 frames[-1].frame)
        return True

    # ------------------------------------------------------------------ control
    def stop(self) -> None:
        """Finish the current frame, then flush and close everything (safe from a signal handler)."""
        self._stop.set()
        stop = getattr(self.source, "stop", None)
        if stop is not None:
            stop()

    def install_signal_handlers(self) -> None:
        """SIGINT/SIGTERM: clean shutdown. SIGUSR1: print the timing report to stderr now."""
        if threading.current_thread() is not threading.main_thread():
            return
        signal.signal(signal.SIGINT, lambda *_: self.stop())
        signal.signal(signal.SIGTERM, lambda *_: self.stop())
        if hasattr(signal, "SIGUSR1"):
            signal.signal(signal.SIGUSR1, lambda *_: self._emit_report())

    def _emit_report(self) -> None:
        # os.write: safe even if the signal interrupted a print on the same stream
        os.write(2, (self.report() + "\n").encode())
        self._write_stats()

    def _write_stats(self) -> None:
        if self.stats_file is None:
            return
        tmp = self.stats_file.with_name(self.stats_file.name + ".tmp")
        tmp.write_text(json.dumps(self.stats()))
        os.replace(tmp, self.stats_file)

    def _error(self, kind: str, detail: str) -> None:
        self.errors[kind] += 1
        now = time.monotonic()
        if now - self._error_log.get(kind, -1e9) > 2.0:
            log.warning("%s: %s (%d so far)", kind, detail, self.errors[kind])
            self._error_log[kind] = now

    def _skip_if_stale(self, frame: MarkerFrame) -> bool:
        """True (and counted) when a newer frame is already waiting: solve that one instead."""
        if self._pending is None or self._solver is None or not self._pending():
            return False
        self.stale += 1
        now = time.monotonic()
        last_time, last_count = self._stale_logged
        if now - last_time > 5.0:
            log.warning("solver behind the stream: skipped %d stale frames in the last %.0f s (%d so far, "
                        "last frame %d); solving the newest", self.stale - last_count,
                        min(now - last_time, now - self._started), self.stale, frame.frame)
            self._stale_logged = (now, self.stale)
        return True

    # ------------------------------------------------------------------ the loop
    def solve_frame(self, frame: MarkerFrame) -> SolveResult | None:
        """Stabilise and solve one frame. A solver with ``latency_frames`` L returns the weights of the
        frame L steps back; they are published with that frame's number, time, head pose and markers
        (so sinks get weights and pose in step), and its first L outputs, which belong to no frame, are not."""
        t0 = time.perf_counter()
        local, R, t = self._stabiliser.step(frame.positions, frame.valid)
        target = np.where(frame.valid[:, None], local - self._neutral, 0.0)
        t_step = time.perf_counter()
        try:
            w = np.array(self._solver.step(target, frame.valid), dtype=float)  # a copy: sinks may encode later
        except Exception as exc:  # a solver bug must not end a live session
            self._error("solver_error", f"frame {frame.frame}: {type(exc).__name__}: {exc}")
            return None
        self._lagged.append((frame, local, R, t, target))  # only frames the solver has seen
        self._step_time = time.perf_counter() - t_step
        self.timing["step"].add(self._step_time)
        if len(self._lagged) < self._lagged.maxlen:
            return None
        return self._result(self._lagged[0], w, t0)

    def _result(self, lagged: tuple, w: np.ndarray, t0: float) -> SolveResult | None:
        frame, local, R, t, target = lagged
        valid = frame.valid
        if not np.isfinite(w).all():
            self._error("solver_nonfinite", f"frame {frame.frame}: solver returned NaN/inf")
            return None
        rms, at_bound = self._fit_quality(self._basis, w, target, valid, *self._bounds)
        solve_time = time.perf_counter() - t0
        self.timing["solve"].add(solve_time)
        return SolveResult(frame.frame, frame.timestamp, self._names, w, to_quaternion(R), t,
                           rms, solve_time, local, valid, at_bound, frame.received)

    def _drain(self) -> None:
        """When the session ends, the last frames a solver with latency L still holds: each is solved by
        stepping on frames with no marker seen (the filter predicts), so every frame solved is published."""
        lagged = getattr(self, "_lagged", None)  # a pipeline that relays weights solves nothing
        if getattr(self, "_solver", None) is None or not lagged or lagged.maxlen == 1:
            return
        lag = lagged.maxlen - 1
        pending = list(self._lagged)[-min(len(self._lagged), lag):]
        pad_valid = np.zeros(len(pending[-1][0].valid), bool)
        pad_target = np.zeros_like(pending[-1][4])
        skip = lag - len(pending)  # pad outputs that still belong to no frame (fewer frames seen than the lag)
        for entry in [None] * skip + pending:
            t0 = time.perf_counter()
            try:
                w = np.array(self._solver.step(pad_target, pad_valid), dtype=float)
            except Exception as exc:
                self._error("solver_error", f"draining the last frames: {type(exc).__name__}: {exc}")
                return
            if entry is not None:
                res = self._result(entry, w, t0)
                if res is not None:
                    self.publish(res)
        self._lagged.clear()

    def publish(self, result: SolveResult) -> None:
        t0 = time.perf_counter()
        for sink in self.sinks:
            try:
                sink.publish(result)
            except Exception as exc:  # one broken sink must not stop the others or the solver
                self._error("sink_error", f"{type(sink).__name__}: {type(exc).__name__}: {exc}")
        self.timing["publish"].add(time.perf_counter() - t0)
        self.frames_out += 1

    def flush(self) -> None:
        for r in self._recorders():
            try:
                r.flush()
            except OSError as exc:
                self._error("recorder_error", f"{type(r).__name__}: {exc}")

    def _recorders(self) -> list:
        out = [s for s in self.sinks if hasattr(s, "flush")]
        if self.marker_recorder is not None:
            out.append(self.marker_recorder)
        return out

    def run(self) -> dict:
        """Run until the source ends, :meth:`stop` is called, or ``max_frames``; then flush and close."""
        self._started = time.monotonic()
        self._cpu0 = time.process_time()
        last_flush = last_stats = time.monotonic()
        try:
            for frame in self.source:
                if frame.received is None:
                    frame.received = time.time()  # a float: the time of day only where a timecode is written
                self.timing["receive"].add(getattr(self.source, "last_decode_seconds", 0.0))
                self.frames_in += 1
                if self.marker_recorder is not None:
                    self.marker_recorder.record(frame)
                if self._solver is None:
                    self._buffer.append(frame)
                    if len(self._buffer) >= self.calibrate_frames and self._calibrate():
                        pending, self._buffer = self._buffer, []
                        for f in pending:
                            res = self.solve_frame(f)
                            if res is not None:
                                self.publish(res)
                elif not self._skip_if_stale(frame):
                    t_frame = time.perf_counter()
                    res = self.solve_frame(frame)
                    if res is not None:
                        self.publish(res)
                        spent = time.perf_counter() - t_frame + getattr(self.source, "last_decode_seconds", 0.0)
                        self.timing["frame"].add(spent)
                        self.timing["around_step"].add(spent - self._step_time)
                now = time.monotonic()
                if now - last_flush >= self.flush_every:
                    self.flush()
                    last_flush = now
                if self.stats_every and now - last_stats >= self.stats_every:
                    if self.stats_file is not None:
                        self._write_stats()
                    else:
                        self._emit_report()
                    last_stats = now
                if self._stop.is_set() or (self.max_frames and self.frames_in >= self.max_frames):
                    break
            self._drain()
        finally:
            self.close()
        return self.stats()

    def close(self) -> None:
        self.flush()
        for s in [*self.sinks, self.marker_recorder]:
            if s is None:
                continue
            try:
                s.close()
            except Exception as exc:
                self._error("close_error", f"{type(s).__name__}: {exc}")
        close = getattr(self.source, "close", None)
        if close is not None:
            close()
        self._write_stats()

    # ------------------------------------------------------------------ reporting
    def stats(self) -> dict:
        bad = getattr(self.source, "bad", None)
        elapsed = max(time.monotonic() - self._started, 1e-9) if self._started else 0.0
        return {
            "mode": self.solver_mode,
            "frames_in": self.frames_in,
            "frames_out": self.frames_out,
            "stale": self.stale,
            "pending_calibration": len(self._buffer),
            "seconds": elapsed,
            "cpu_seconds": time.process_time() - self._cpu0 if self._started else 0.0,
            "timing": {s: t.percentiles() for s, t in self.timing.items()},
            "bad_input": bad.as_dict() if bad is not None else {},
            "errors": dict(self.errors),
            "sinks": {f"{type(s).__name__}:{i}": s.stats() for i, s in enumerate(self.sinks) if hasattr(s, "stats")},
            "marker_recorder": self.marker_recorder.stats() if self.marker_recorder is not None else None,
        }

    def report(self) -> str:
        st = self.stats()
        lines = [f"frames in {st['frames_in']}, out {st['frames_out']}, {st['seconds']:.1f} s, "
                 f"driver CPU {st['cpu_seconds']:.2f} s, mode {st['mode'] or self.mode + ' (not calibrated)'}"]
        if self.skip_stale:
            lines.append(f"stale frames skipped (solver behind the stream): {st['stale']}")
        lines.append(f"{'stage':10s} {'p50 ms':>9s} {'p99 ms':>9s} {'max ms':>9s}")
        for s, p in st["timing"].items():
            lines.append(f"{s:10s} {p['p50_ms']:9.3f} {p['p99_ms']:9.3f} {p['max_ms']:9.3f}")
        bad = st["bad_input"]
        lines.append("bad input: " + (", ".join(f"{k} {v}" for k, v in sorted(bad.items())) if bad else "none"))
        if st["errors"]:
            lines.append("errors: " + ", ".join(f"{k} {v}" for k, v in sorted(st["errors"].items())))
        for name, s in st["sinks"].items():
            lines.append(f"sink {name}: " + ", ".join(f"{k} {v}" for k, v in s.items()))
        if st["marker_recorder"]:
            lines.append("marker recorder: " + ", ".join(f"{k} {v}" for k, v in st["marker_recorder"].items()))
        return "\n".join(lines)
