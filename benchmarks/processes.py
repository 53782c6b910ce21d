"""Helper processes of the live benchmarks: real drivers, senders and receivers on loopback."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def spawn(args: list, **kw) -> subprocess.Popen:
    """``python ARGS...`` with the project importable; stdout/stderr piped as text."""
    return subprocess.Popen([sys.executable, *map(str, args)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env={**os.environ, "PYTHONPATH": os.pathsep.join(
                                filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}, **kw)


def first_line(proc: subprocess.Popen) -> str:
    """The next line a helper prints (its 'ready' line); its stderr tail if it exited instead."""
    line = proc.stdout.readline().strip()
    if not line:
        raise RuntimeError(f"{proc.args[:4]} exited: {proc.stderr.read()[-2000:]}")
    return line


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
