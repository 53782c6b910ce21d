"""``livecap review``: review and edit a solved take in the browser (docs/review.md).

Scrub the take, compare the solve with ground truth, make spacetime edits (Seol §6), drag points
of the face (direct manipulation, Lewis & Anjyo 2010) and reduce the curves to keys (Lewis §5.4).
"""

from __future__ import annotations

import argparse
import webbrowser

from livecap.cli.common import add_calibration_arguments, add_rig_arguments
from livecap.cli.retarget_args import add_retarget_arguments


def register(sub) -> None:
    p = sub.add_parser("review", help="review and edit a solved take in the browser (scrub, edit, drag, keys)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("take", help="marker take: .c3d, .trc or .csv")
    add_rig_arguments(p)
    add_calibration_arguments(p)
    p.add_argument("--weights", help="solved weights CSV (default: solve the take in --mode)")
    p.add_argument("--mode", default="movement", help="solver mode when no --weights (default movement)")
    p.add_argument("--truth", help="ground truth .npz (default: <take>.truth.npz when present)")
    p.add_argument("--port", type=int, default=8765, help="port (default 8765; 0 picks a free one)")
    p.add_argument("--interface", default="127.0.0.1", help="address to bind (default 127.0.0.1: this machine only)")
    p.add_argument("--pull", type=float, default=1.0, help="direct manipulation: pull towards the current weights")
    p.add_argument("--journal", help="edit journal (default <take>.review-edits beside the take; replayed on reopen)")
    p.add_argument("--no-browser", action="store_true", help="only print the URL")
    add_retarget_arguments(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import asyncio
    import secrets
    import socket

    import numpy as np

    from livecap.review.guard import allowed_hosts
    from livecap.review.load import open_session
    from livecap.review.server import make_app
    from transport.gltf import glb_bytes
    from transport.takefile import is_weights_take

    sock = socket.socket(socket.AF_INET6 if ":" in args.interface else socket.AF_INET)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((args.interface, args.port))
    except OSError as exc:
        raise OSError(f"--port {args.port}: cannot listen on {args.interface} ({exc.strerror})") from None
    session = _weights_session(args) if is_weights_take(args.take) else open_session(
        args.take, args.rig, args.markers, args.profile, args.weights, args.truth, args.mode, args.neutral_seconds,
        args.pull)
    _journal(session, args)
    rest = np.zeros((1, len(session.names)))
    host, port = sock.getsockname()[:2]
    token = secrets.token_urlsafe(24)  # this run's secret: only the printed URL carries it
    app = make_app(session, glb_bytes(session.rig, session.names, np.zeros(1), rest, name="rig"), token,
                   allowed_hosts(host, port, _machine_names() if host in ("0.0.0.0", "::") else ()))
    sock.listen(128)  # connections queue from here on, before the URL is printed
    url = f"http://{'[' + host + ']' if ':' in host else host}:{port}/?token={token}"
    print(f"livecap review: {session.n_frames} frames x {len(session.names)} shapes at {url}", flush=True)
    if not args.no_browser:
        try:
            webbrowser.open(url)
        except webbrowser.Error:
            pass
    asyncio.run(_serve(app, sock))
    return 0


def _weights_session(args: argparse.Namespace):
    """A Live Link Face CSV onto the rig (by name, --map or --transfer); the markers the edits need are the
    rig's own, or with --transfer the ICT face's sites on it."""
    from livecap.cli.retarget_args import load_target, retargeter
    from livecap.retarget.take import retarget_curves
    from livecap.review.load import weights_session
    from transport.llf_csv import read_llf_csv

    rig, layout = load_target(args)
    retarget = retargeter(args, rig, layout)
    layout = getattr(retarget, "layout", layout)
    if layout is None:
        raise ValueError(f"{args.rig}: reviewing a Live Link Face CSV needs the rig's markers (for the edits): give "
                         "--markers, or --transfer")
    return weights_session(rig, layout, retarget_curves(read_llf_csv(args.take), retarget), args.pull)


def _machine_names() -> tuple[str, ...]:
    """This machine's name and addresses: how other machines reach a server bound to every interface."""
    import socket

    name = socket.gethostname()
    try:
        addresses = {a[4][0].split("%")[0] for a in socket.getaddrinfo(name, None)}
    except OSError:
        addresses = set()
    return (name, *sorted(addresses))


def _journal(session, args: argparse.Namespace) -> None:
    """Attach the edit journal, replaying a previous run's edits on the same take (one line said)."""
    import sys
    from pathlib import Path

    from livecap.review.journal import fingerprint, open_journal

    path = Path(args.journal) if args.journal else Path(args.take + ".review-edits")
    try:
        journal, aside = open_journal(path, fingerprint(session.names, session.weights))
    except OSError as exc:
        if args.journal:
            raise OSError(f"--journal {path}: cannot write ({exc.strerror})") from None
        print(f"livecap review: warning: edits will not survive a restart: cannot write {path} "
              f"({exc.strerror}); pass --journal PATH", file=sys.stderr)
        return
    if aside:
        print(f"livecap review: {aside}", flush=True)
    n = session.attach_journal(journal)
    if n or journal.skipped:
        print(f"livecap review: replayed {n} journal entries (edits, undos, redos) from {path}"
              + (f"; skipped a corrupt tail of {journal.skipped} lines" if journal.skipped else ""), flush=True)


async def _serve(app, sock) -> None:
    import asyncio

    from aiohttp import web

    runner = web.AppRunner(app, access_log=None)
    await runner.setup()
    await web.SockSite(runner, sock).start()
    try:
        await asyncio.Event().wait()
    finally:
        await runner.cleanup()
