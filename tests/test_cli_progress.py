"""Progress feedback (livecap/cli/progress.py): on stderr, no live bar when stderr is not a
terminal, one summary line per long step; stdout keeps only the command's own output."""

import os
import pty
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _short_take(tmp_path, demo):
    from livecap.demo.performance import PerformanceSettings, perform
    from transport.takefile import write_take

    rig, layout = demo
    path = tmp_path / "short.c3d"
    write_take(perform(rig, layout, PerformanceSettings(seconds=1.5, occlusion=0.05, seed=4)).take, path)
    return path


def _solve_cmd(take, out):
    return [sys.executable, "-m", "livecap", "solve", str(take), "--rig", str(ROOT / "recordings" / "demo_rig.npz"),
            "--out", str(out), "--mode", "qp"]


def test_piped_solve_prints_summaries_on_stderr_and_no_bar(tmp_path, demo):
    take = _short_take(tmp_path, demo)
    r = subprocess.run(_solve_cmd(take, tmp_path / "w.csv"), capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    lines = r.stderr.strip().splitlines()
    assert any(line.startswith("calibrating and tuning on the take") and " s" in line for line in lines), lines
    assert any(line.startswith("solving (qp): 180/180 in ") for line in lines), lines
    assert "\x1b[" not in r.stderr and "━" not in r.stderr  # no live display when not a terminal
    assert "solving" not in r.stdout and "w.csv" in r.stdout


def test_on_a_terminal_the_bar_is_drawn_and_the_summary_stays(tmp_path, demo):
    take = _short_take(tmp_path, demo)
    pid, fd = pty.fork()
    if pid == 0:  # child: stdout and stderr are the pseudo-terminal
        os.execv(sys.executable, _solve_cmd(take, tmp_path / "w.csv"))
    out = b""
    while True:
        try:
            chunk = os.read(fd, 65536)
        except OSError:
            break
        if not chunk:
            break
        out += chunk
    _, status = os.waitpid(pid, 0)
    text = out.decode("utf-8", "replace")
    assert os.waitstatus_to_exitcode(status) == 0, text[-2000:]
    assert "\x1b[" in text  # rich drew a live display
    assert "solving (qp): 180/180 in " in text
