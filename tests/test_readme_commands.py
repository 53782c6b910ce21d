"""Every command of the README's command table: ``--help``, and a run on the bundled demo (exit 0, no traceback).

The runs use the demo the generator writes (``generate`` is itself a row), with the smallest settings
that still exercise each command, so the whole file stays quick.
"""

import argparse
import json
import re
from pathlib import Path
from urllib.request import Request, urlopen

import pytest

from livecap.cli import build_parser, main
from transport.recorders import MarkerRecorder
from transport.takefile import read_take

ROOT = Path(__file__).resolve().parents[1]


def table_commands() -> list[str]:
    """Command names in the README table's first column (``rom``, ``composite``, ``map`` rows split)."""
    table = ROOT.joinpath("README.md").read_text().split("## Commands", 1)[1].split("\n## ", 1)[0]
    names = []
    for row in re.findall(r"^\| (`livecap .*?) \| ", table.replace("\\|", "/"), re.M):
        for code in re.findall(r"`([^`]*)`", row):
            words = code.removeprefix("livecap ").split()
            names.append(" ".join(words[:2]) if words[0] in ("rig", "markers") else words[0])
    return names


# each row's run on the demo; "{rec}" is the generated demo folder
RUNS = {
    "generate": ["generate", "--out", "rec", "--seconds", "2"],
    "demo": ["demo", "--recordings", "rec", "--mode", "qp", "--out", "demo.csv"],
    "info": ["info", "rec/demo_rig.npz"],
    "solve": ["solve", "rec/demo_take.c3d", "--rig", "rec/demo_rig.npz", "--mode", "qp", "--out", "w.csv"],
    "export": ["export", "w.csv", "--rig", "rec/demo_rig.npz", "--out", "take.glb"],
    "rig import": ["rig", "import", "take.glb", "--out", "imported.npz"],
    "rig animate": ["rig", "animate", "take.glb", "--weights", "w.csv", "--out", "animated.glb"],
    "calibrate": ["calibrate", "rec/demo_neutral.c3d", "--rig", "rec/demo_rig.npz", "--out", "actor.npz"],
    "calibration-report": ["calibration-report", "rec/demo_take.c3d", "--rig", "rec/demo_rig.npz", "--mode", "qp",
                           "--stride", "8"],
    "evaluate": ["evaluate", "rec/demo_take.c3d", "--rig", "rec/demo_rig.npz", "--profile", "actor.npz",
                 "--modes", "qp"],
    "edit": ["edit", "w.csv", "--take", "rec/demo_take.c3d", "--rig", "rec/demo_rig.npz", "--profile", "actor.npz",
             "--edit", "100:jawOpen=0.9@90-110", "--out", "e.csv"],
    "run": ["run", "--replay", "rec/demo_take.c3d", "--fast", "--max-frames", "60", "--rig", "rec/demo_rig.npz",
            "--profile", "actor.npz", "--record-csv", "live.csv", "--csv-layout", "livelinkface"],
    "batch": ["batch", "rec/demo_take.c3d", "--rig", "rec/demo_rig.npz", "--profile", "actor.npz", "--mode", "qp",
              "--workers", "1", "--out", "batch"],
    "recover": ["recover", "killed.npz.partial"],
    "review": ["review"],  # a server until stopped: tests/review_server.py runs it on the demo take
    "label": ["label", "rec/demo_take.c3d", "--profile", "actor.npz", "--out", "labelled.c3d"],
    "pose": ["pose", "--rig", "rec/demo_rig.npz", "--pin", "marker:{marker}=0,0,0", "--out", "pose.csv"],
    # the live session's Live Link Face CSV stands in for a real performance (the app's own layout)
    "prior": ["prior", "build", "live.csv", "--rig", "rec/demo_rig.npz", "--out", "prior.npz"],
    "realeval": ["realeval", "--curves", "live.csv", "--rig", "demo", "--seconds", "0.5", "--start", "0",
                 "--noise", "0.5", "--modes", "lsq", "--no-prior"],
    "send": ["send", "rec/demo_take.c3d", "--osc", "127.0.0.1:39999", "--fast", "--frames", "30"],
    "replay": ["replay", "rec/demo_take.c3d", "--rig", "rec/demo_rig.npz", "--profile", "actor.npz", "--mode", "qp",
               "--frames", "png", "--every", "120", "--size", "160x120"],
    "rig transfer": ["rig", "transfer", "--generic", "rec/demo_rig.npz", "--target", "objrig/neutral.obj",
                     "--out", "transferred"],
    "markers bind": ["markers", "bind", "rec/demo_take.c3d", "--rig", "rec/demo_rig.npz", "--out", "bound.json"],
    "rom": ["rom", "--out", "rom", "--rate", "30"],
    "composite": ["composite", "--demo", "--out", "composite"],
    "map": ["map", "w.csv", "--out", "mapped.csv"],
    "noise-study": ["noise-study", "--rig", "rec/demo_rig.npz", "--seconds", "2", "--modes", "lsq", "--no-sweep",
                    "--plot", ""],
    "fig11": ["fig11", "--seconds", "2", "--out-dir", "fig11"],
}


def test_the_table_lists_every_command_and_each_has_a_run():
    names = table_commands()
    assert "demo" in names and "calibrate" in names and "rig transfer" in names
    assert set(names) == set(RUNS), "a README command without a demo run here, or the reverse"
    registered = set(build_parser()._subparsers._group_actions[0].choices)
    assert {n.split()[0] for n in names} <= registered


def _undocumented(name: str, parser) -> list[str]:
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub, p in action.choices.items():
                out += _undocumented(f"{name} {sub}", p)
        elif action.option_strings and action.dest != "help" and not action.help:
            out.append(f"{name} {action.option_strings[0]}")
    return out


def test_every_option_has_a_help_text():
    commands = build_parser()._subparsers._group_actions[0].choices
    assert [o for n, p in commands.items() for o in _undocumented(n, p)] == []


@pytest.mark.parametrize("name", sorted(RUNS))
def test_help_says_what_each_option_is_for(name, capsys):
    with pytest.raises(SystemExit) as done:
        main([*name.split(), "--help"])
    assert done.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: livecap")


def _killed_journal(path: str) -> None:
    """What a ``run --record-markers`` killed mid-session leaves: a journal, never closed."""
    take = read_take("rec/demo_take.c3d")
    rec = MarkerRecorder(path.removesuffix(".partial"), take.labels, take.rate)
    for _, frame in zip(range(30), take.frames(), strict=False):
        rec.record(frame)
    rec.fh.flush()


def test_every_command_runs_on_the_demo(tmp_path, monkeypatch, capsys, review_server):
    monkeypatch.chdir(tmp_path)
    first = ["generate", "demo", "info", "solve", "calibrate", "run"]
    order = first + [n for n in sorted(RUNS) if n not in first]
    for name in order:
        if name == "review":  # a server: the shared test process on the demo take answers its page and API
            meta = Request(review_server.base + "/api/meta", headers={"X-Livecap-Token": review_server.token})
            with urlopen(review_server.url, timeout=30) as page, urlopen(meta, timeout=30) as api:
                assert page.status == 200 and json.load(api)["n_frames"] > 0
            continue
        if name == "rig transfer":
            assert main(["generate", "--out", "rec", "--seconds", "2", "--obj-rig", "objrig"]) == 0
        if name == "recover":
            _killed_journal("killed.npz.partial")
        marker = read_take("rec/demo_take.c3d").labels[10] if name == "pose" else ""
        code = main([a.format(marker=marker) for a in RUNS[name]])
        err = capsys.readouterr().err
        assert code == 0, f"livecap {name}: {err}"
        assert "Traceback" not in err
