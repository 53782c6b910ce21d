"""The ``livecap`` command. Each subcommand lives in its own module with ``register(subparsers)``."""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

# Module names under livecap.cli; each adds its subcommands.
COMMANDS = [
    "demo",
    "solve",
    "info",
    "generate",
    "replay",
    "edit",
    "fig11",
    "evaluate",
    "composite",
    "rom",
    "map",
    "run",
    "send",
    "noise_study",
    "calibrate",
    "rig",
    "batch",
    "export",
    "recover",
    "review",
    "pose",
    "realeval",
    "label",
    "prior",
    "markers",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="livecap",
        description="Facial performance capture: labelled markers in, blendshape weights out.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"livecap.cli.{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except (ValueError, OSError) as exc:  # file and input problems: one clear line, no traceback
        if args.verbose:
            raise
        print(f"livecap {args.command}: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
