"""The rooms' import rules (livecap/__init__.py): solvers import nothing of livecap, transport or
viewer; transport and viewer import only livecap.core of livecap; core imports nothing above it.
Read from the source (every import statement, function-level ones included), not from sys.modules."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _imports(package: str) -> list[tuple[str, str]]:
    found = []
    for path in sorted((ROOT / package).rglob("*.py")):
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                found += [(str(path.relative_to(ROOT)), a.name) for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                found.append((str(path.relative_to(ROOT)), node.module))
    return found


def _violations(package: str, allowed) -> list[str]:
    ours = {"livecap", "solvers", "transport", "viewer"}
    return [f"{f}: {m}" for f, m in _imports(package) if m.split(".")[0] in ours and not allowed(m)]


@pytest.mark.parametrize("package, allowed", [
    ("solvers", lambda m: m.startswith("solvers")),
    ("transport", lambda m: m.startswith(("transport", "livecap.core"))),
    ("viewer", lambda m: m.startswith(("viewer", "livecap.core", "solvers.rigid"))),
    ("livecap/core", lambda m: m.startswith(("livecap.core", "solvers"))),
])
def test_rooms_import_only_what_they_may(package, allowed):
    assert _violations(package, allowed) == []


def test_livecap_top_level_holds_only_packages():
    loose = sorted(p.name for p in (ROOT / "livecap").glob("*.py") if p.name not in {"__init__.py", "__main__.py"})
    assert loose == []


def test_the_rule_catches_a_forbidden_import(tmp_path, monkeypatch):
    """The checker itself: a transport module importing the pipeline is reported."""
    (tmp_path / "transport").mkdir()
    (tmp_path / "transport" / "bad.py").write_text("def f():\n    from livecap.live.pipeline import Pipeline\n")
    monkeypatch.setitem(globals(), "ROOT", tmp_path)
    assert _violations("transport", lambda m: m.startswith(("transport", "livecap.core"))) != []


# ``__main__`` is the command's entry point.
CLI_IMPORTERS = {"livecap/__main__.py"}


def _cli_or_argparse(m: str) -> bool:
    return m == "argparse" or m == "livecap.cli" or m.startswith("livecap.cli.")


def test_only_the_command_speaks_argparse():
    """No module outside livecap/cli/ imports livecap.cli or argparse: the library is below the command."""
    found = {f for f, m in _imports("livecap") if _cli_or_argparse(m) and not f.startswith("livecap/cli/")}
    assert found - CLI_IMPORTERS == set()
    assert CLI_IMPORTERS - found == set(), "an exemption no longer needed: remove it from CLI_IMPORTERS"


def test_the_argparse_rule_catches_a_library_module(tmp_path, monkeypatch):
    (tmp_path / "livecap" / "review").mkdir(parents=True)
    (tmp_path / "livecap" / "review" / "load.py").write_text("import argparse\nfrom livecap.cli import common\n")
    monkeypatch.setitem(globals(), "ROOT", tmp_path)
    assert {m for _, m in _imports("livecap") if _cli_or_argparse(m)} == {"argparse", "livecap.cli"}


def test_calibration_sits_below_offline():
    """Calibration is what offline solving uses, so it imports nothing of livecap.offline (nor the demo)."""
    assert [f"{f}: {m}" for f, m in _imports("livecap/calibration")
            if m.startswith(("livecap.offline", "livecap.demo", "livecap.cli"))] == []


def test_capture_sources_import_no_circle():
    """transport/capture.py chooses a source and the sources import what they share from
    transport/capture_queue.py (issue 38: capture.py and natnet.py/qtm.py imported each other)."""
    capture = {"transport.capture", "transport.capture_queue", "transport.natnet", "transport.natnet_frame",
               "transport.qtm"}
    edges: dict[str, set[str]] = {}
    for f, m in _imports("transport"):
        if m in capture and f[:-3].replace("/", ".") in capture:
            edges.setdefault(f[:-3].replace("/", "."), set()).add(m)
    circles = sorted({tuple(sorted((a, b))) for a, targets in edges.items() for b in targets
                      if a in edges.get(b, set())})
    assert circles == []
