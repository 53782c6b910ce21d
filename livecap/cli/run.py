"""``livecap run``: a live session. Markers in (ZeroMQ, OSC or a paced take), weights out.

Set-up on the command line or in a TOML session file (``--session``, see livecap/live/session.py);
command-line options win. Prints one ``ready`` line when every socket is bound (with the real
endpoints, so port 0 / ``*`` work), a timing report on SIGUSR1, and the report on exit.
Ctrl-C or SIGTERM stops cleanly: every recorder is flushed and closed.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from livecap.calibration.profile import Profile, calibrate, estimate_neutral
from livecap.cli.common import load_rig, tune_on_take
from livecap.cli.retarget_args import add_retarget_arguments
from livecap.live.checks import check_overlap, check_profile_rig
from livecap.live.pipeline import Pipeline
from livecap.live.session import load_session
from livecap.modes.registry import DEFAULT_MODE, MODE_HELP, MODES_AND_AUTO

log = logging.getLogger(__name__)

_PARSER: argparse.ArgumentParser | None = None
FIRST_FRAME_GRACE = 10.0  # seconds a session with --idle-timeout waits for its first frame by default


def register(sub) -> None:
    global _PARSER
    p = sub.add_parser("run", help="live session: markers in (ZeroMQ/OSC/take), weights out (ZeroMQ/VMC/Live Link)",
                       description=__doc__.split("\n\n")[0])
    p.add_argument("--session", help="TOML session file with any of these options")
    src = p.add_argument_group("source (one of)")
    src.add_argument("--zmq-in", help="ZeroMQ address to SUBscribe to (connects; e.g. tcp://127.0.0.1:5555)")
    src.add_argument("--zmq-in-bind", action="store_true", help="bind the SUB socket instead of connecting")
    src.add_argument("--osc-in", help="[HOST:]PORT to receive OSC frame bundles on")
    src.add_argument("--replay", help="take to replay at its own pace (.c3d, .trc, .csv, raw .npz recording)")
    src.add_argument("--lsl-in", help="Lab Streaming Layer marker stream name (labels from its description)")
    src.add_argument("--qtm-in", help="Qualisys QTM RT server HOST[:PORT] (3D, or 3D-no-labels with --unlabelled)")
    src.add_argument("--natnet-in", help="OptiTrack Motive NatNet server HOST[:PORT] (unicast; metres)")
    src.add_argument("--livelink-in", help="[HOST:]PORT to receive Live Link Face UDP on (the iPhone app's ARKit "
                     "weights and head angles; no --profile/--rig needed; docs/iphone.md)")
    src.add_argument("--unlabelled", action="store_true",
                     help="the source's points are unlabelled (or wrongly named): label them against --profile")
    src.add_argument("--speed", type=float, default=1.0, help="replay speed factor (default 1)")
    src.add_argument("--fast", action="store_true", help="replay as fast as possible")
    src.add_argument("--loop", action="store_true", help="replay in a loop")
    src.add_argument("--start", type=int, help="first frame number to replay")
    src.add_argument("--end", type=int, help="frame number to stop before")
    src.add_argument("--rate", type=float, default=120.0, help="stream frame rate for network sources (default 120)")
    src.add_argument("--idle-timeout", type=float,
                     help="end the session after this many seconds without a frame (network sources)")
    src.add_argument("--first-frame-timeout", type=float,
                     help="end the session when no frame came this many seconds after start (default: with "
                          "--idle-timeout, the larger of it and 10 s: senders often start after the driver)")
    src.add_argument("--skip-stale", action=argparse.BooleanOptionalAction, default=None,
                     help="when the solver falls behind, solve only the newest waiting frame and count the skipped "
                          "ones as stale, so latency stays bounded (default: on for --zmq-in/--osc-in, off for "
                          "--replay, where every frame is solved)")
    src.add_argument("--actor", default="actor", help="actor name in topics (markers.<actor>, weights.<actor>)")
    src.add_argument("--interface", help="allow binding/connecting this non-loopback interface (default: "
                     "127.0.0.1 only)")
    cal = p.add_argument_group("calibration")
    cal.add_argument("--profile", help="calibrated profile (.npz); without it, calibrate on the stream's start")
    cal.add_argument("--rig", help="rig (OBJ folder or .npz) to calibrate against when there is no --profile")
    cal.add_argument("--markers", help="markers.json (default: beside the rig)")
    cal.add_argument("--neutral-seconds", type=float, default=1.0,
                     help="seconds at the start of the stream taken as the neutral face (default 1)")
    add_retarget_arguments(p)
    p.add_argument("--smooth", default="none", help="--livelink-in: filter the weights and head as the marker path "
                   "does: none (default, no lag), 1e (1€ filter, causal) or N (fixed lag of N frames; docs/iphone.md)")
    sol = p.add_argument_group("solver")
    sol.add_argument("--mode", default=DEFAULT_MODE, choices=sorted(MODES_AND_AUTO), help=MODE_HELP)
    sol.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                     help="solver option (repeatable), e.g. --option ridge=0.01")
    out = p.add_argument_group("sinks")
    out.add_argument("--zmq-out", help="ZeroMQ address to publish weights.<actor> on (binds; port 0 or * = any)")
    out.add_argument("--zmq-hwm", type=int, default=100, help="send high-water mark in messages (default 100)")
    out.add_argument("--zmq-policy", default="fair", choices=["count", "fair"],
                     help="fair (default): libzmq drops only for a full subscriber, the others get every frame; "
                          "count: drop for everyone and count it when any subscriber is full")
    out.add_argument("--header-every", type=float, default=1.0, help="re-send the shape names every S seconds")
    out.add_argument("--lsl-out", help="Lab Streaming Layer outlet name for weights and head pose")
    out.add_argument("--vmc", help="[HOST:]PORT to send VMC (OSC) to (VMC's port is 39539)")
    out.add_argument("--vmc-arkit", action="store_true", help="same as --vmc-perfect-sync")
    out.add_argument("--vmc-perfect-sync", action="store_true",
                     help="send VMC shapes under Perfect Sync names (the 52 ARKit shapes as EyeBlinkLeft, ...)")
    out.add_argument("--vmc-vrm", type=int, choices=[0, 1],
                     help="send VMC VRM expression presets (VRM 0.x: A, Blink_L, Joy...; 1.0: aa, blinkLeft, happy...)")
    out.add_argument("--vrm-map", help="JSON table VRM 1.0 expression -> {ARKit term: coefficient} (docs/protocol.md)")
    out.add_argument("--livelink", help="[HOST:]PORT to send Live Link Face UDP to (Unreal's port is 11111)")
    out.add_argument("--livelink-subject", help="Live Link subject name (default: --actor)")
    out.add_argument("--timecode", default="clock",
                     help="Live Link / CSV timecode: 'clock' (system time of day, default), HH:MM:SS:FF (start "
                          "there) or 'take' (the take's own timestamps)")
    out.add_argument("--arkit-map", help="JSON mapping ARKit name -> rig shape name(s), for non-ARKit rigs")
    out.add_argument("--window", action="store_true", help="live preview window of the solve (needs a display and "
                     "--rig; drops frames, never slows the solver)")
    out.add_argument("--window-optional", action="store_true",
                     help="like --window, but carry on without it when there is no display")
    rec = p.add_argument_group("recorders")
    rec.add_argument("--record-csv", help="weights CSV (Live Link Face layout when the names are ARKit)")
    rec.add_argument("--csv-layout", default="auto", choices=["auto", "livecap", "livelinkface"],
                     help="--record-csv columns: livecap (frame,time,shapes), livelinkface (Live Link Face CSV), "
                     "auto (livelinkface for an ARKit rig; default)")
    rec.add_argument("--record-jsonl", help="weights as JSON lines")
    rec.add_argument("--record-markers", help="raw incoming markers (.npz or .c3d) for exact replay")
    rec.add_argument("--flush-every", type=float, default=0.1, help="recorder flush interval in seconds")
    rec.add_argument("--fsync", action="store_true", help="fsync recorders on every flush (survives power loss)")
    sec = p.add_argument_group("CurveZMQ (optional)")
    sec.add_argument("--curve-secret", help="our secret certificate (.key_secret)")
    sec.add_argument("--curve-clients", help="folder of allowed client public certificates (for bound sockets)")
    sec.add_argument("--curve-server", help="server public certificate (for connecting sockets)")
    mon = p.add_argument_group("monitoring")
    mon.add_argument("--stats-file", help="write the stats as JSON here (periodically, on SIGUSR1, at exit)")
    mon.add_argument("--stats-every", type=float, help="report every S seconds")
    mon.add_argument("--max-frames", type=int, help="stop after this many input frames")
    p.set_defaults(func=run)
    _PARSER = p


def _parse_value(text: str):
    import tomllib

    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def _apply_session(args: argparse.Namespace) -> dict:
    options: dict = {}
    if args.session:
        known = {a.dest for a in _PARSER._actions} - {"help", "session", "func"}
        settings, options = load_session(args.session, known)
        for dest, value in settings.items():
            if getattr(args, dest) == _PARSER.get_default(dest):
                setattr(args, dest, value)
    for kv in args.option:
        if "=" not in kv:
            raise ValueError(f"--option {kv!r}: expected KEY=VALUE")
        k, v = kv.split("=", 1)
        options[k.strip()] = _parse_value(v.strip())
    return options


def _curve(args):
    from transport.security import curve_from_flags

    return curve_from_flags(args.curve_secret, args.curve_clients, args.curve_server)


def build(args: argparse.Namespace) -> tuple[Pipeline, list[str]]:
    """The pipeline and a description of its endpoints (what the ``ready`` line prints)."""
    from transport.security import udp_address, zmq_address

    options = _apply_session(args)
    sources = [x for x in (args.zmq_in, args.osc_in, args.replay, args.lsl_in, args.qtm_in, args.natnet_in,
                           args.livelink_in) if x]
    if len(sources) != 1:
        raise ValueError("give exactly one source: --zmq-in, --osc-in, --replay, --lsl-in, --qtm-in, --natnet-in "
                         "or --livelink-in")
    if args.unlabelled and not (args.profile and not (args.zmq_in or args.osc_in)):
        raise ValueError("--unlabelled needs --profile and a source other than --zmq-in/--osc-in (they carry labels)")
    profile = rig = layout = None
    want_window = args.window or args.window_optional
    if want_window and not args.rig:
        raise ValueError("--window needs --rig: the window draws the rig's mesh (a profile holds none)")
    if (args.map or args.transfer is not None) and not (args.livelink_in and args.rig):
        raise ValueError("--map and --transfer retarget ARKit curves: they need --livelink-in and --rig")
    if args.smooth != "none" and not args.livelink_in:
        raise ValueError("--smooth filters an incoming weights stream (--livelink-in); a marker solve has --mode")
    retarget = None
    if args.livelink_in and args.rig:
        from livecap.cli.retarget_args import load_target, retargeter

        rig, layout = load_target(args)
        retarget = retargeter(args, rig, layout)
        labels = []
    elif args.profile:
        profile = Profile.load(args.profile)
        labels = profile.labels
        if want_window or args.rig:
            rig, layout = load_rig(args)
            check_profile_rig(profile, rig, args.profile, args.rig)
    elif args.rig:
        rig, layout = load_rig(args)
        labels = list(layout.labels)
    elif args.livelink_in:
        labels = []
    else:
        raise ValueError("give --profile, or --rig to calibrate on the start of the stream")
    curve = _curve(args)
    described = []
    rate = args.rate
    if args.replay:
        from transport.replay import ReplaySource, open_take
        from transport.takefile import size_problem

        if args.unlabelled:
            source = ReplaySource.open(args.replay, None, speed=args.speed,
                                       fast=args.fast, loop=args.loop, start=args.start, end=args.end)
        else:
            take, frames, timestamps = open_take(args.replay)
            stable = profile.stable if profile is not None else layout.stable
            check_overlap(take.labels, labels, stable, args.replay, args.profile or args.rig)
            problem = size_problem(take.select(labels))
            if problem:
                raise ValueError(f"{args.replay}: {problem}")
            source = ReplaySource(take, labels, speed=args.speed, fast=args.fast, loop=args.loop, start=args.start,
                                  end=args.end, frames=frames, timestamps=timestamps)
        rate = source.rate
        described.append(f"replay {args.replay}")
    elif args.zmq_in:
        from transport.zmq_source import ZmqSource

        addr = zmq_address(args.zmq_in, args.interface)
        source = ZmqSource(addr, labels, args.actor, bind=args.zmq_in_bind, curve=curve,
                           idle_timeout=args.idle_timeout, first_frame_timeout=_first_frame_timeout(args))
        described.append(f"zmq-in {addr}")
    elif args.lsl_in:
        from transport.lsl import LslMarkerSource, confine

        confine(args.interface)
        source = LslMarkerSource(args.lsl_in, None if args.unlabelled else labels, idle_timeout=args.idle_timeout)
        if source.labels is None and not args.unlabelled:
            raise ValueError(f"LSL stream {args.lsl_in!r} has no marker labels: give --unlabelled and --profile")
        rate = source.rate or rate
        described.append(f"lsl-in {args.lsl_in}")
    elif args.qtm_in or args.natnet_in:
        from transport.capture import capture_source

        source, what = capture_source(args.qtm_in, args.natnet_in, labels, args.unlabelled, args.idle_timeout,
                                      args.interface)
        described.append(what)
    elif args.livelink_in:
        from transport.livelink import DEFAULT_PORT
        from transport.livelink_source import LiveLinkFaceSource

        host, port = udp_address(args.livelink_in, DEFAULT_PORT, args.interface)
        source = LiveLinkFaceSource(host, port, idle_timeout=args.idle_timeout,
                                    first_frame_timeout=_first_frame_timeout(args))
        rate = 60.0  # the app's frame rate (its packets say 60/1)
        described.append(f"livelink-in {host}:{source.port}")
    else:
        from transport.osc_source import OscSource

        host, port = udp_address(args.osc_in, 0, args.interface)
        source = OscSource(host, port, labels, idle_timeout=args.idle_timeout,
                           first_frame_timeout=_first_frame_timeout(args))
        described.append(f"osc-in {host}:{source.port} (receive buffer {source.rcvbuf >> 10} KiB)")
    if args.unlabelled:
        from livecap.live.unlabelled import LabelledSource

        source = LabelledSource(source, profile)
        described[-1] += " (unlabelled)"

    mapping = None
    if args.arkit_map or args.map:  # a rig reached by --map speaks ARKit to the sinks through the same file
        from transport.arkit import load_mapping

        mapping = load_mapping(args.arkit_map or args.map)
    sinks: list = []
    neutral_frames = max(1, int(round(args.neutral_seconds * rate)))
    if args.timecode not in ("clock", "take"):
        from livecap.core.timecode import parse_timecode

        parse_timecode(args.timecode, rate)
    if args.zmq_out:
        from transport.zmq_sink import ZmqSink

        addr = zmq_address(args.zmq_out, args.interface)
        sink = ZmqSink(addr, args.actor, hwm=args.zmq_hwm, policy=args.zmq_policy, header_every=args.header_every,
                       curve=curve, rate=rate)
        sinks.append(sink)
        described.append(f"zmq-out {sink.address}")
    if args.lsl_out:
        from transport.lsl import LslWeightSink, confine

        confine(args.interface)
        sinks.append(LslWeightSink(args.lsl_out, profile.names if profile else rig.names if rig else source.names,
                                   rate))
        described.append(f"lsl-out {args.lsl_out}")
    if args.vmc:
        from transport.vmc import DEFAULT_PORT, VmcSink

        host, port = udp_address(args.vmc, DEFAULT_PORT, args.interface)
        from transport.vrm import load_vrm_table

        names = f"vrm{args.vmc_vrm}" if args.vmc_vrm is not None else (
            "perfect-sync" if args.vmc_perfect_sync or args.vmc_arkit else "rig")
        table = load_vrm_table(args.vrm_map) if args.vrm_map else None
        sinks.append(VmcSink(host, port, mapping=mapping, where=str(args.arkit_map), names=names, vrm_table=table,
                             neutral_frames=neutral_frames))
        described.append(f"vmc {host}:{port}")
    if args.livelink:
        from transport.livelink import DEFAULT_PORT, LiveLinkSink

        host, port = udp_address(args.livelink, DEFAULT_PORT, args.interface)
        sinks.append(LiveLinkSink(host, port, args.livelink_subject or args.actor, mapping, fps=rate,
                                  where=str(args.arkit_map), timecode=args.timecode, actor=args.actor,
                                  neutral_frames=neutral_frames))
        described.append(f"livelink {host}:{port}")
    from transport.recorders import CsvRecorder, JsonlRecorder, MarkerRecorder

    if args.record_csv:
        sinks.append(CsvRecorder(args.record_csv, rate, args.csv_layout, mapping, fsync=args.fsync,
                                 timecode=args.timecode, neutral_frames=neutral_frames))
        described.append(f"csv {args.record_csv}")
    if args.record_jsonl:
        sinks.append(JsonlRecorder(args.record_jsonl, fsync=args.fsync))
        described.append(f"jsonl {args.record_jsonl}")
    marker_recorder = None
    if args.record_markers:
        marker_recorder = MarkerRecorder(args.record_markers, labels, rate, fsync=args.fsync)
        described.append(f"markers {args.record_markers}")

    window = _window(args, rig, layout, profile) if want_window else None
    if window is not None:
        sinks.append(window)
        described.append(f"window {window.size[0]}x{window.size[1]}")

    if not sinks:
        log.warning("no output: the solved weights go nowhere (give --zmq-out, --vmc, --livelink, --record-csv, "
                    "--record-jsonl or --window)")
    calibrator = None
    if profile is None:
        def calibrator(take, rig=rig, layout=layout):
            calibrated = calibrate(rig, layout, estimate_neutral(take, layout.stable))
            tune_on_take(calibrated, take)  # what every calibration path stores: the noise estimate
            if window is not None:  # the window shows the actor's markers from now on
                window.set_profile(calibrated)
            return calibrated

    if args.livelink_in:
        from livecap.live.relay import WeightsPipeline

        return WeightsPipeline(source, sinks, retarget, args.smooth, rate=rate, flush_every=args.flush_every,
                               max_frames=args.max_frames,
                               stats_file=args.stats_file, stats_every=args.stats_every), described
    pipeline = Pipeline(source, sinks, profile=profile, calibrator=calibrator,
                        calibrate_frames=max(1, int(round(args.neutral_seconds * rate))), labels=labels, rate=rate,
                        mode=args.mode, options=options, marker_recorder=marker_recorder,
                        flush_every=args.flush_every, max_frames=args.max_frames, stats_file=args.stats_file,
                        stats_every=args.stats_every,
                        skip_stale=(not args.replay) if args.skip_stale is None else args.skip_stale)
    return pipeline, described


def _first_frame_timeout(args: argparse.Namespace) -> float | None:
    if args.first_frame_timeout is not None:
        return args.first_frame_timeout
    return max(args.idle_timeout, FIRST_FRAME_GRACE) if args.idle_timeout else None


def _window(args: argparse.Namespace, rig, layout, profile):
    """The live preview sink (viewer/window.py), or None with --window-optional and no display."""
    from viewer.window import NoDisplay, WindowSink

    try:
        return WindowSink(rig, layout, profile, title=f"livecap run - {args.mode}")
    except NoDisplay as exc:
        if not args.window_optional:
            raise
        print(f"livecap run: {exc}; carrying on without the window", file=sys.stderr)
        return None


def run(args: argparse.Namespace) -> int:
    import signal

    import zmq

    from viewer.errors import NoDisplay

    if hasattr(signal, "SIGUSR1"):  # a report request while sockets come up must not kill the session
        signal.signal(signal.SIGUSR1, signal.SIG_IGN)
    try:
        pipeline, described = build(args)
    except NoDisplay as exc:  # --window without a display: one line, exit 2 (a usage problem, not a bad file)
        print(f"livecap run: {exc}", file=sys.stderr)
        return 2
    except zmq.ZMQError as exc:  # port in use, endpoint libzmq refuses: one line, no traceback
        print(f"livecap run: error: ZeroMQ: {exc}", file=sys.stderr)
        return 1
    pipeline.install_signal_handlers()
    print("ready: " + "; ".join(described), flush=True)
    pipeline.run()
    print(pipeline.report(), flush=True)
    if args.record_markers and not Path(args.record_markers).exists():
        print(f"livecap run: no frames recorded to {args.record_markers}", file=sys.stderr)
    lost = getattr(pipeline.source, "lost", None)
    if lost:  # the capture system went away and did not come back: not a finished session
        print(f"livecap run: error: source lost: {lost}", file=sys.stderr)
        return 1
    return 0
