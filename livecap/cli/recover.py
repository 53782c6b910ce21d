"""``livecap recover FILE.partial``: the final raw-marker recording from the journal a killed
``livecap run --record-markers`` left behind (transport/recorders.py)."""

from __future__ import annotations

import argparse


def register(sub) -> None:
    p = sub.add_parser("recover", help="rebuild a raw marker recording (.npz/.c3d) from its .partial journal")
    p.add_argument("journal", help="the FILE.partial journal left by a killed session")
    p.add_argument("--out", help="recording to write (default: the journal's name without .partial)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from transport.recorders import recover_marker_journal_report

    out, rec = recover_marker_journal_report(args.journal, args.out)
    print(f"recovered {rec.take.n_frames} frames from {args.journal} to {out}: {rec.journal_report()}")
    return 0
