"""A real ``livecap review`` process on a free port for the review tests (API and browser)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


class ReviewServer:
    """``livecap review`` on the demo take (a neutral-take profile and the qp solve: the fastest start),
    killed on close. ``url`` is the printed one (with the token), ``base`` the server's root."""

    def __init__(self, workdir: Path, *extra: str, journal: Path | None = None, take: Path | None = None,
                 rig: Path | None = None) -> None:
        """The demo take and rig unless ``take`` and ``rig`` are given (then calibrated on the take's start)."""
        self.journal = journal or workdir / "take.review-edits"  # never beside the repository's demo take
        if take is None:
            rig = ROOT / "recordings/demo_rig.npz"
            take = ROOT / "recordings/demo_take.c3d"
            profile = workdir / "actor.npz"  # calibrated on the neutral take: no tuning on the take at start-up
            if not profile.exists():
                subprocess.run([sys.executable, "-m", "livecap", "calibrate",
                                str(ROOT / "recordings/demo_neutral.c3d"), "--rig", str(rig), "--out", str(profile)],
                               check=True, capture_output=True, timeout=300)
            extra = ("--profile", str(profile), *extra)
        cmd = [sys.executable, "-m", "livecap", "review", str(take), "--rig", str(rig), "--mode", "qp",
               "--port", "0", "--no-browser", "--journal", str(self.journal), *extra]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                     env={**os.environ, "PYTHONUNBUFFERED": "1"})
        start = time.monotonic()
        self.notices = []
        line = self.proc.stdout.readline()
        while line and "http://" not in line and len(self.notices) < 5:
            self.notices.append(line.strip())
            line = self.proc.stdout.readline()
        if "http://" not in line:
            self.close()
            raise RuntimeError(f"livecap review did not start: {line!r} {self.proc.stderr.read()[-2000:]}")
        self.url = line.split(" at ")[-1].strip()
        self.base, _, self.token = self.url.partition("?token=")
        self.base = self.base.rstrip("/")
        self.startup = time.monotonic() - start

    def request(self, path: str, body: object = None, client: str = "", headers: dict | None = None):
        """(status, decoded body) of one request with the session's token (JSON POST when ``body``)."""
        head = {"X-Livecap-Token": self.token, "X-Livecap-Client": client, **(headers or {})}
        data = None
        if body is not None:
            data = json.dumps(body).encode()
            head.setdefault("Content-Type", "application/json")
        status, raw, ctype = self.raw(path, data, head)
        return status, json.loads(raw) if ctype == "application/json" else raw

    def get(self, path: str):
        """The decoded body of a GET with the session's token, which must succeed (200)."""
        status, body = self.request(path)
        assert status == 200, body
        return body

    def raw(self, path: str, data: bytes | None, headers: dict) -> tuple[int, bytes, str]:
        """(status, body, content type) of a request with exactly these headers (no token unless given)."""
        req = urllib.request.Request(self.base + path, data, headers)
        try:
            with urllib.request.urlopen(req, timeout=60) as r:
                return r.status, r.read(), r.headers.get_content_type()
        except urllib.error.HTTPError as exc:
            return exc.code, exc.read(), exc.headers.get_content_type()

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
