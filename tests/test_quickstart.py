"""docs/quickstart.md as a user runs it: every command in its sh blocks, in order, in an empty folder."""

import re
import shlex
import subprocess
import sys
from pathlib import Path

DOC = Path(__file__).resolve().parents[1] / "docs" / "quickstart.md"


def commands() -> list[list[str]]:
    blocks = re.findall(r"```sh\n(.*?)```", DOC.read_text(), re.S)
    return [shlex.split(line) for block in blocks for line in block.splitlines() if line.strip()]


def test_every_command_of_the_walk_through_runs(tmp_path):
    cmds = commands()
    assert len(cmds) >= 8 and all(c[0] == "livecap" for c in cmds)
    for cmd in cmds:
        r = subprocess.run([sys.executable, "-m", "livecap", *cmd[1:]], cwd=tmp_path, capture_output=True,
                           text=True, timeout=600)
        assert r.returncode == 0, f"{shlex.join(cmd)}\n{r.stderr}"
        assert "Traceback" not in r.stderr, shlex.join(cmd)
        if cmd[1] == "run":
            assert "sent 120" in r.stdout and "LiveLinkSink" in r.stdout and "VmcSink" in r.stdout
    assert (tmp_path / "myrig" / "neutral.obj").exists() and (tmp_path / "myrig" / "markers.json").exists()
    assert (tmp_path / "rom" / "myrig_rom.keys.json").exists()
    header = (tmp_path / "weights.csv").read_text().splitlines()[0]
    assert header.startswith("frame,time,") and "jawOpen" in header
