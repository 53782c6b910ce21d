"""A real ``livecap review`` process on a free port for the review tests (API and browser)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


class ReviewServer:
    """``livecap review`` on the demo take (a neutral-take profile and the qp solve: the fastest start),
    killed on close."""

    def __init__(self, workdir: Path, *extra: str) -> None:
        rig = str(ROOT / "recordings/demo_rig.npz")
        profile = workdir / "actor.npz"  # calibrated on the neutral take: no tuning on the take at start-up
        subprocess.run([sys.executable, "-m", "livecap", "calibrate", str(ROOT / "recordings/demo_neutral.c3d"),
                        "--rig", rig, "--out", str(profile)], check=True, capture_output=True, timeout=300)
        cmd = [sys.executable, "-m", "livecap", "review", str(ROOT / "recordings/demo_take.c3d"), "--rig", rig,
               "--profile", str(profile), "--mode", "qp", "--port", "0", "--no-browser", *extra]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                     env={**os.environ, "PYTHONUNBUFFERED": "1"})
        start = time.monotonic()
        line = self.proc.stdout.readline()
        if "http://" not in line:
            self.close()
            raise RuntimeError(f"livecap review did not start: {line!r} {self.proc.stderr.read()[-2000:]}")
        self.url = line.split(" at ")[-1].strip()
        self.startup = time.monotonic() - start

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
